"""CFD-DEM coupling (unresolved, OpenFOAM gas phase).

Kept import-light on purpose: import the submodules you need, e.g.
``from coupling.mesh import read_polymesh``, ``from coupling import voidfraction``.

Particle-to-mesh submodules:

* ``coupling.mesh``          ASCII polyMesh reader, OpenFOAM geometry, point location
* ``coupling.voidfraction``  void fraction (centre / divided / smoothed) and
                             conservative per-cell accumulation of exchange terms
* ``coupling.drag``          drag correlations (Di Felice, Gidaspow, Beetstra, ...)
* ``coupling.interpolate``   cell-centre fields to particle positions

Coupled runs: ``coupling.interface`` (one coupling step), ``coupling.case`` (case files,
validation, checks), ``coupling.run`` (the ``coupling`` command).
"""
