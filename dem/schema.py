"""The declared state: one row per array of a run, and the bundles the kernels take.

Every array a run holds is declared here once, with what it needs:

* ``owner``: ``particle`` (one row per particle, owned rows then ghosts; trailing axes may be
  per wall: ``W``), ``pair`` (one row per particle, one column per neighbour slot ``S``,
  aligned with the half neighbour list ``nb``), ``wall`` (one row per wall row: a mesh wall has
  several, dem.contact.mesh), ``mesh`` (the triangle meshes, in the Walls bundle), ``table``
  (material and gas tables), ``param`` (switches, scalars, run totals);
* ``dtype`` and ``tail`` (the shape after the first axis: numbers, ``"W"`` = one per wall,
  ``"Q"`` = one per wall candidate (as many as walls), ``"S"`` = neighbour slots, None = set by the
  scene);
* ``when``: the feature that enables it (see :func:`features`); a disabled array is an empty
  array of the same dtype and number of axes (zero rows), so every scene gives the kernels
  the same types and one cached kernel serves them all;
* ``ghost`` (copied to the neighbouring ranks' ghost rows at each exchange), ``forward``
  (refreshed in the ghosts every step: which message), ``sort`` (permuted by the spatial
  sort), ``migrate`` (travels with a particle to another rank), ``checkpoint`` (the key it is
  saved under; the keys of checkpoint format 1), ``scratch`` (contents need not survive a
  reordering: left as it is), ``output`` (its name in VTK output and ``final.npz``),
  ``record`` (contact history that survives a rebuild on another rank or a restart on any
  number of ranks as an id-keyed record, dem.parallel.records: ``odd`` = a vector that
  changes sign with the pair's orientation, ``even`` = does not).

Sorting, migration, ghost messages, checkpoints, restarts and output iterate over
:data:`FIELDS`; the kernels take the named bundles :class:`Particles`, :class:`Pairs`,
:class:`Walls`, :class:`Tables` and :class:`Params`, whose members are the rows of each owner
in the order declared here.
"""
from collections import namedtuple

import numpy as np

F8 = np.dtype(np.float64)
I8 = np.dtype(np.int64)
I4 = np.dtype(np.int32)
U1 = np.dtype(np.uint8)
B1 = np.dtype(np.bool_)


class Field(namedtuple("Field", "name owner dtype tail when ghost forward sort migrate checkpoint "
                                "scratch output kernel record doc",
                       defaults=((), None, False, None, None, None, None, False, None, True, None, ""))):
    """One declared array (see the module docstring); every column after ``dtype`` has a
    default (sort and migrate: None = by owner, see :func:`_f`)."""

    def shape(self, rows, walls=1, slots=1):
        """Full shape for ``rows`` rows (per-wall / per-slot axes filled in)."""
        sub = {"W": max(int(walls), 1), "Q": max(int(walls), 1), "S": max(int(slots), 1), None: 1}
        return (int(rows),) + tuple(sub.get(t, t) for t in self.tail)

    def empty(self):
        """The disabled form: zero rows, same dtype and number of axes."""
        return np.zeros(self.shape(0), self.dtype)


def _f(name, owner, dtype, tail=(), **columns):
    """One row of :data:`FIELDS`: the columns of :class:`Field` by keyword, their defaults
    declared there; sort (None) = per-row arrays (particle, pair), migrate (None) = particle arrays."""
    f = Field(name, owner, np.dtype(dtype), tuple(tail), **columns)
    return f._replace(sort=owner in ("particle", "pair") if f.sort is None else f.sort,
                      migrate=owner == "particle" if f.migrate is None else f.migrate)


FIELDS = (
    # ---------------------------------------------------------------- particles (mechanics)
    _f("id", "particle", I8, ghost=True, checkpoint="state_id", kernel=False, output="id",
       doc="global particle id"),
    _f("position", "particle", F8, (3,), ghost=True, forward="motion", checkpoint="state_position",
       output="position", doc="centre (m)"),
    _f("velocity", "particle", F8, (3,), ghost=True, forward="motion", checkpoint="state_velocity",
       output="velocity", doc="m/s"),
    _f("angular_velocity", "particle", F8, (3,), ghost=True, forward="motion",
       checkpoint="state_angular_velocity", output="angular_velocity", doc="rad/s"),
    _f("radius", "particle", F8, ghost=True, checkpoint="state_radius", output="radius", doc="m"),
    _f("mass", "particle", F8, ghost=True, checkpoint="state_mass", doc="kg"),
    _f("inv_mass", "particle", F8, ghost=True, checkpoint="state_inv_mass", doc="1/kg"),
    _f("inv_inertia", "particle", F8, ghost=True, checkpoint="state_inv_inertia",
       doc="1 / (2/5 m R^2), 1/(kg m^2)"),
    _f("material", "particle", I4, ghost=True, checkpoint="state_material", output="material",
       doc="material index"),
    _f("group", "particle", I4, ghost=True, checkpoint="state_group", kernel=False,
       doc="insertion group (heat sources by group)"),
    _f("force", "particle", F8, (3,), checkpoint="state_force", doc="total force of the last evaluation (N)"),
    _f("torque", "particle", F8, (3,), checkpoint="state_torque", doc="N m"),
    _f("x_build", "particle", F8, (3,), checkpoint="state_x_build",
       doc="position at the last neighbour build (rebuild test)"),
    _f("external_force", "particle", F8, (3,), when="fluid", doc="fluid force of a coupled run (N), "
       "set by the coupling before each interval (not checkpointed: the coupling state is); with the "
       "drag coefficient below, the explicit part only: beta u_f + pressure-gradient / buoyancy force"),
    _f("drag_beta", "particle", F8, when="fluid", doc="beta_p (kg/s) of the coupled run's drag "
       "beta_p (u_f - v), taken implicitly in the particle velocity by each half kick (set by the coupling "
       "before each interval with external_force; not checkpointed: the coupling state is)"),
    _f("external_torque", "particle", F8, (3,), when="fluid_torque", doc="fluid torque of a coupled run "
       "(N m) with rotational drag (coupling.toml torque), set by the coupling before each interval (not "
       "checkpointed): the explicit part k_rot Omega_f, Omega_f = curl(u_f) / 2 at the particle"),
    _f("rot_drag", "particle", F8, when="fluid_torque", doc="k_rot (N m s) of the fluid torque "
       "k_rot (Omega_f - omega), taken implicitly in the angular velocity by each half kick (set with "
       "external_torque; not checkpointed)"),
    _f("inv_mass_eff", "particle", F8, when="virtual_mass", doc="1 / (m + C_vm rho_f V_p) (1/kg): the "
       "translational half kicks of a coupled run with virtual mass (coupling.toml virtual_mass) take the "
       "-C_vm rho_f V_p dv/dt part implicitly by this effective mass (set by the coupling; not checkpointed)"),
    _f("cg", "particle", F8, when="coarse_graining", ghost=True, checkpoint="state_cg", output="coarse_graining",
       doc="coarse-graining factor: the parcel stands for cg^3 real particles of radius radius / cg"),
    # ---------------------------------------------------------------- particles (heat)
    _f("temperature", "particle", F8, when="heat", ghost=True, forward="temperature",
       checkpoint="state_temperature", output="temperature", doc="K"),
    _f("heat_rate", "particle", F8, when="heat", checkpoint="state_heat_rate", output="heat_rate",
       doc="net heat rate of the last step (W)"),
    _f("inv_heat_capacity", "particle", F8, when="heat", ghost=True, checkpoint="state_inv_heat_capacity",
       doc="1 / (m c), 1/(J/K)"),
    _f("por", "particle", F8, when="heat", ghost=True, forward="porosity", checkpoint="th_por",
       doc="porosity around the particle (global, local, Voronoi or the CFD void fraction)"),
    _f("qgen", "particle", F8, when="friction_heat", checkpoint="th_qgen", doc="friction heat of the step (W)"),
    _f("tf", "particle", F8, when="heat", checkpoint="th_tf", doc="gas temperature at the particle (K)"),
    _f("uf", "particle", F8, (3,), when="heat", checkpoint="th_uf", doc="gas velocity at the particle (m/s)"),
    _f("qsrc", "particle", F8, when="group_sources", checkpoint="th_qsrc", doc="heat source by group (W)"),
    _f("qmech", "particle", F8, (7,), when="heat_output", checkpoint="th_qmech",
       doc="the heat rate of the last step by mechanism (W; columns dem.thermal.heat.QM: direct, indirect, wall, "
           "convection, radiation, generation, sources; [output] heat_by_mechanism): they sum to heat_rate"),
    _f("work", "particle", F8, (3,), when="heat", scratch=True, forward="rate",
       doc="heat-step scratch: start temperature, cross-rank rate, explicit flux"),
    # ---------------------------------------------------------------- particle x wall
    _f("wnb", "particle", I4, ("Q",), checkpoint="wnb", doc="walls within reach (candidate list)"),
    _f("wnn", "particle", I4, checkpoint="wnn", doc="number of wall candidates"),
    _f("whist", "particle", F8, ("W", 3), checkpoint="whist", doc="tangential spring per wall (m)"),
    _f("wrhist", "particle", F8, ("W", 3), when="epsd", checkpoint="wrhist", doc="rolling spring per wall"),
    _f("wage", "particle", F8, ("W", 2), when="contact_age", checkpoint="th_wage",
       doc="contact age and impact speed per wall"),
    _f("Hw", "particle", F8, ("Q",), when="heat", checkpoint="th_Hw",
       doc="wall conductance per candidate (W/K; contact area for a fixed-flux wall)"),
    _f("Hwg", "particle", F8, ("Q",), when="indirect", checkpoint="th_Hwg",
       doc="the part of Hw across the gas gap (indirect conduction, W/K)"),
    _f("mcon", "particle", F8, ("W", 4), when="mesh", checkpoint="mcon",
       doc="contact with a mesh wall's row: distance from the centre (inf: none), unit normal towards the "
           "surface (dem.contact.mesh.mesh_contacts; the normal is how the next step finds the same contact)"),
    _f("mtri", "particle", I4, (8,), when="mesh",
       doc="the triangles of every mesh wall within reach + skin of the particle at the last neighbour build, by "
           "index (dem.contact.mesh.mesh_candidates; what the contacts of each step look at). Not saved: a "
           "restart finds them again from the build's positions and time (x_build, fp_tbuild)"),
    _f("mtn", "particle", I4, when="mesh",
       doc="how many of mtri are used; -1: more than its columns (the bins are searched at each step)"),
    # ---------------------------------------------------------------- pairs (neighbour slots)
    _f("nb", "pair", I4, ("S",), checkpoint="nb", doc="half neighbour list (row of the other particle)"),
    _f("nnb", "pair", I4, checkpoint="nnb", doc="used slots of each row"),
    _f("hist", "pair", F8, ("S", 3), checkpoint="hist", record="odd", doc="tangential spring (m)"),
    _f("rhist", "pair", F8, ("S", 3), when="epsd", checkpoint="rhist", record="odd", doc="rolling spring"),
    _f("age", "pair", F8, ("S", 2), when="contact_age", checkpoint="age", record="even", doc="contact age (s), impact speed"),
    _f("Hd", "pair", F8, ("S",), when="heat", checkpoint="Hd", doc="direct conductance (W/K)"),
    _f("Hi", "pair", F8, ("S",), when="indirect", checkpoint="Hi", doc="indirect conductance (W/K)"),
    _f("rnear", "pair", U1, ("S",), when="radiation", checkpoint="rnear", doc="within the radiation range"),
    # ---------------------------------------------------------------- walls
    _f("wf", "wall", F8, (None,), doc="geometry and motion (columns: dem.contact.walls WF)"),
    _f("wi", "wall", I8, (None,), doc="type and material (columns: dem.contact.walls WI)"),
    _f("wth", "wall", F8, (5,), doc="thermal condition, temperature, flux, table length, emissivity (columns: dem.thermal.heat WT)"),
    _f("wtab", "wall", F8, (None, 2), doc="temperature table [time, T]"),
    _f("wtot", "wall", F8, (), checkpoint="th_wtot", doc="heat through each wall since the start (J)"),
    _f("wgap", "wall", F8, (), checkpoint="th_wgap",
       doc="the part of wtot across the gas gap (indirect conduction, J); the rest went through the contacts"),
    _f("wrad", "wall", F8, (), checkpoint="th_wrad",
       doc="the part of wtot by radiation (a fixed-temperature wall with an emissivity, J)"),
    # ---------------------------------------------------------------- triangle meshes (dem.contact.mesh)
    # every mesh of the scene, concatenated, in its reference frame; set up from the scene, never
    # saved (a restart reads the mesh files again and checks their digest: dem.checkpoint)
    _f("mv", "mesh", F8, (3,), when="mesh", doc="vertices (m)"),
    _f("mfc", "mesh", I8, (3,), when="mesh", doc="triangles: their three vertices"),
    _f("mev", "mesh", I8, (3,), when="mesh", doc="triangles holding each edge (corner k to k + 1)"),
    _f("mvv", "mesh", I8, when="mesh", doc="triangles holding each vertex"),
    _f("mm", "mesh", F8, (None,), when="mesh", doc="per mesh: motion and bins (columns: dem.contact.mesh MM)"),
    _f("mmi", "mesh", I8, (None,), when="mesh", doc="per mesh: rows and bins (columns: dem.contact.mesh MMI)"),
    _f("mpl", "mesh", F8, (4,), when="mesh", doc="triangles: unit normal n and offset n . a of their plane (the "
       "step's pre-test: a triangle whose plane is beyond the sphere cannot touch it)"),
    _f("mkeys", "mesh", I8, when="mesh", doc="occupied bins of each mesh, sorted"),
    _f("mstart", "mesh", I8, when="mesh", doc="each mesh's bin k: triangles mitems[mstart[k0 + m + k]:... + 1]"),
    _f("mitems", "mesh", I8, when="mesh", doc="the triangles of the bins"),
    _f("mdense", "mesh", I4, when="mesh", doc="each mesh's bin grid as a dense map, cell -> its bin in mkeys (-1: "
       "empty), for the grids of at most dem.contact.mesh.DENSE_MAX cells (MMI.d0)"),
    _f("mstamp", "mesh", I8, when="mesh", scratch=True, doc="search scratch: a tag per triangle, the last tag at the end"),
    _f("mout", "mesh", I8, when="mesh", scratch=True, doc="search scratch: the candidate triangles"),
    _f("mraw", "mesh", F8, (8,), when="mesh", scratch=True, doc="search scratch: the candidates' closest points"),
    # ---------------------------------------------------------------- tables
    _f("tab", "table", F8, (None, None), doc="pair tables E*, G*, damping, mu, mu_r, c_t/c_n [6, mat, mat] (slots: dem.step TAB)"),
    _f("tmat", "table", F8, (None,), doc="thermal material table (dem.thermal.registry)"),
    _f("gas", "table", F8, doc="gas and model parameters (dem.thermal.registry)"),
    _f("ereal", "table", F8, (None,), doc="real effective modulus per material pair (Pa)"),
    _f("keff", "table", F8, (None,), doc="series conductivity per material pair (W/(m K))"),
    _f("rcf", "table", F8, (None,), doc="contact-radius factor per material pair of a correction: rc = rcf sqrt(R* delta) "
       "(dem.thermal.contact_radius.hertz_radius_factor)"),
    # ---------------------------------------------------------------- parameters
    _f("ip", "param", I8, doc="integer switches (slots: dem.step IP)"),
    _f("fp", "param", F8, doc="float parameters (slots: dem.step FP)"),
    _f("thi", "param", I8, doc="thermal switches (slots: dem.thermal.heat TI)"),
    _f("thf", "param", F8, doc="thermal floats (slots: dem.thermal.heat TF)"),
    _f("lo", "param", F8, doc="domain lower corner (m)"),
    _f("hi", "param", F8, doc="domain upper corner (m)"),
    _f("periodic", "param", B1, doc="periodic axes"),
    _f("srcbox", "param", F8, (7,), doc="volumetric heat-source boxes: min, max, W/m^3"),
    _f("tot", "param", F8, checkpoint="th_tot", doc="heat per mechanism since the start (J; slots: dem.thermal.heat TOT)"),
    _f("flow", "param", F8, (None, 3), when="flow", checkpoint="flow_tot", kernel=False,
       doc="particles that entered by each inlet, then left by each outlet: number, mass (kg), enthalpy m c T (J) "
           "since the start (dem.flow; this rank's, summed over the ranks in output and checkpoints)"),
    _f("xcnt", "param", I8, scratch=True,
       doc="pairs across blocks of rows, kept between neighbour builds (dem.step.interact_blocks; slots: XC)"),
)

BY_NAME = {f.name: f for f in FIELDS}


def of(owner, kernel_only=False):
    return tuple(f for f in FIELDS if f.owner == owner and (f.kernel or not kernel_only))


# the owners whose arrays each bundle holds (the meshes travel with the walls)
BUNDLE_OWNERS = {"particle": ("particle",), "pair": ("pair",), "wall": ("wall", "mesh"),
                 "table": ("table",), "param": ("param",)}


def bundle_fields(owner):
    """The declared arrays of the kernels' bundle of ``owner``, in bundle order."""
    return tuple(f for o in BUNDLE_OWNERS[owner] for f in of(o, kernel_only=True))


def _bundle(owner, doc):
    t = namedtuple(owner.capitalize() + "s", [f.name for f in bundle_fields(owner)])
    t.__doc__ = doc
    return t


Particles = _bundle("particle", "Per-particle arrays (owned rows, then ghosts) the kernels read and write.")
Pairs = _bundle("pair", "Neighbour slots: the half list and every array aligned with it.")
Walls = _bundle("wall", "Per-wall geometry, motion, thermal condition and totals; the triangle meshes.")
Tables = _bundle("table", "Material-pair and gas tables.")
Params = _bundle("param", "Switches, scalars, domain and run totals.")

# what enables an array; a feature a scene does not name is off
FEATURES = ("heat", "fluid", "fluid_torque", "virtual_mass", "epsd", "contact_age", "friction_heat",
            "group_sources", "indirect", "radiation", "coarse_graining", "mesh", "flow", "heat_output")


# features a coupling sets before each interval (its arrays are not checkpointed: the coupling
# recomputes them from its own state)
COUPLING_FEATURES = ("fluid", "fluid_torque", "virtual_mass")


def enabled(field, feats):
    return field.when is None or bool(feats.get(field.when, False))


def slots(name, rows, size=None):
    """The slots of a parameter array (``ip``, ``fp``, ``thi``, ...) or the columns of a table,
    declared once: ``rows`` are (slot, meaning) or (slot, width, meaning), in array order.
    Returns a named tuple of each slot's first index, which the kernels read by name
    (``fp[FP.dt]``; a global tuple is a compile-time constant to Numba: the same machine code
    as an integer literal), with ``SIZE`` (the array's length: ``size``, spare slots
    included, or the slots' total width) and ``MEANING`` (slot -> meaning)."""
    names, first, meaning = [], [], {}
    k = 0
    for row in rows:
        slot, width, what = row if len(row) == 3 else (row[0], 1, row[1])
        names.append(slot)
        first.append(k)
        meaning[slot] = what
        k += width
    if size is not None and size < k:
        raise ValueError(f"{name}: {k} slots declared, size {size}")
    t = namedtuple(name, names)
    t.SIZE = k if size is None else size
    t.MEANING = meaning
    t.__doc__ = f"Slots of {name}: " + "; ".join(f"{a} = {i}: {meaning[a]}" for a, i in zip(names, first))
    return t(*first)


# the slots of Params.xcnt: the pairs across blocks of rows, counted once per neighbour list and
# block count (dem.step.interact_blocks): the key they were counted for (block count 0: not
# counted), then each block's first row of interact_blocks' xj / xv; a rebuild (dem.step.after_build)
# or a list set from Python (dem.state) clears the key
XC = slots("XC", (
    ("nblk", "block count of the counts (0: count again)"),
    ("n", "rows (owned and ghosts) of the counts"),
    ("nown", "owned rows of the counts"),
    ("start", "first of the nblk + 1 offsets: block b's pairs across blocks are rows [start + b, start + b + 1)"),
))
