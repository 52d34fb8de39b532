"""CFD-DEM coupling (unresolved, OpenFOAM gas phase).

Kept import-light on purpose: import the submodules you need, e.g.
``from coupling.mesh import read_polymesh``, ``from coupling import voidfraction``.

Particle-to-mesh submodules:

* ``coupling.mesh``          OpenFOAM geometry, point location (``PolyMesh``, ``read_polymesh``)
* ``coupling.polymesh_files`` the ASCII polyMesh files (read, write, structured hex mesh)
* ``coupling.voidfraction``  void fraction (centre / divided / smoothed) and
                             conservative per-cell accumulation of exchange terms
* ``coupling.drag``          drag correlations (Di Felice, Gidaspow, Beetstra, ...)
* ``coupling.interpolate``   cell-centre fields to particle positions

Coupled runs: ``coupling.interface`` (one coupling step), ``coupling.case`` (case files,
validation, checks), ``coupling.run`` (the ``coupling`` command), which wires the stages
``coupling.prepare``, ``coupling.launch``, ``coupling.transport``, ``coupling.loop``,
``coupling.restart`` and ``coupling.diagnostics``; ``coupling.errors`` holds every error.
"""
