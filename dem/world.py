"""The world of a run: what the scene builds and every other part reads.

    world = World(scene)     # state, pair tables, walls, parameters, the thermal model, the clock

Owns the declared state (dem.state.State with its tables, walls and kernel parameters), the
thermal model (dem.thermal.kernel.ThermalModel, or None), the time step and end time, and the
clock (``step_count``, ``time``). It computes nothing per step: the stepper advances the clock,
the checkpointer sets it on a restart (:meth:`World.set_step`).
"""
import math

import numpy as np

from .contact.damping import damping_factor, mixed_tables
from .contact.registry import CONTACT_MODELS, ROLLING_MODELS, DAMPING_MODELS, TANGENTIAL_MODELS
from .contact import walls as W
from .parcels import parcel_factors
from .state import State
from . import step as K


class World:
    def __init__(self, scene):
        from .memory import check_scene
        check_scene(scene)  # refuse a scene larger than the available memory before allocating
        self.scene = scene
        sim = scene.simulation
        self.dt = sim["time_step"]
        if scene.thermal is not None and scene.thermal["time_step"] is not None:
            self.dt = scene.thermal["time_step"]  # frozen packing: the thermal step
        self.step_count = 0
        self.time = 0.0
        self.end_time = sim["end_time"]
        mats = scene.materials
        self.wall_first, self.wall_of_row = W.wall_rows(scene.walls)   # a mesh wall is several rows
        self.state = st = State(scene.id, scene.position, scene.velocity, scene.angular_velocity,
                                scene.radius, scene.material, scene.group, [m["density"] for m in mats],
                                walls=self.wall_of_row.size)
        cgs = parcel_factors(scene)
        if cgs is not None:   # cg = 1 everywhere: exactly the run without
            st.enable(coarse_graining=True)
            st.cg[:] = cgs
        st.lo = np.ascontiguousarray(scene.domain["min"], float)
        st.hi = np.ascontiguousarray(scene.domain["max"], float)
        st.periodic = np.array(scene.domain["periodic"], np.bool_)
        L = st.hi - st.lo
        for k in range(3):  # wrap periodic axes
            if st.periodic[k]:
                st.position[:, k] = st.lo[k] + np.mod(st.position[:, k] - st.lo[k], L[k])
        if getattr(scene, "distributed", False):   # set up per rank (MPI): the run's totals
            self.rmax = float(scene.rmax)
            self.n_total = int(scene.n_total)
        else:
            self.rmax = float(st.radius.max(initial=0.0))
            self.n_total = st.n_owned  # every rank holds the whole scene at this point
        self.rmax = max(self.rmax, scene.flow_rmax)   # the run's largest radius: an inlet's may be larger
        st.tab, self.pair_tables = pair_tables(scene)
        st.wf, st.wi = wall_tables(scene.walls)
        self.nwalls = int(self.wall_of_row.size)   # wall rows (the kernels' walls)
        self.nmeshes = sum(w["type"] == "mesh" for w in scene.walls)
        st.enable(epsd=ROLLING_MODELS[scene.contact["rolling"]] == 2)
        if self.nmeshes:
            st.enable(mesh=True)
            st.mcon[:, :, 0] = math.inf
            self.mesh_cell = 2.0 * self.rmax + float(scene.simulation["neighbor_skin"])
            self.mesh_held = mesh_tables(st, scene.walls, self.mesh_cell)
            self.mesh_until = math.inf   # (the whole mesh; a rank's part: hold_mesh_near)
        self.wall_speed = max([wall_surface_speed(w) for w in scene.walls], default=0.0)
        st.ip, st.fp = self._params()
        self.thermal = None
        if scene.thermal is not None:
            from .thermal.kernel import ThermalModel
            self.thermal = ThermalModel(scene, st, self.rmax)
        else:
            from .thermal.kernel import no_heat_tables
            no_heat_tables(st)
        self.flow = None
        if scene.inlets or scene.outlets:   # particles enter and leave (dem.flow)
            from .flow import Flow
            self.flow = Flow(self)
        self.reach = self.thermal.reach if self.thermal is not None else 0.0
        st.fp[K.FP.reach] = self.reach
        # how far beyond contact a coupled run's particle void fraction looks for neighbours
        # (coupling.particle_void): the ghost layer covers it; the pair list does not
        reach_of = getattr(scene, "ghost_reach", None)
        self.ghost_reach = float(reach_of(self.rmax)) if callable(reach_of) else 0.0

    def _params(self):
        sc = self.scene
        ip = np.zeros(K.IP.SIZE, np.int64)
        ip[K.IP.contact] = CONTACT_MODELS[sc.contact["model"]]
        ip[K.IP.rolling] = ROLLING_MODELS[sc.contact["rolling"]]
        ip[K.IP.tangential] = TANGENTIAL_MODELS[sc.contact["tangential"]]
        ip[K.IP.nwalls] = self.nwalls
        ip[K.IP.nmesh] = self.nmeshes
        from .flow import open_faces
        ip[K.IP.openfaces] = open_faces(sc.outlets)
        ip[K.IP.mech] = 1 if sc.simulation["mechanics"] else 0
        ip[K.IP.nown] = self.state.n_owned
        ip[K.IP.threads] = 1
        fp = np.zeros(K.FP.SIZE)
        fp[K.FP.dt] = self.dt
        fp[K.FP.gx:K.FP.gz + 1] = sc.simulation["gravity"]
        fp[K.FP.skin] = sc.simulation["neighbor_skin"]
        fp[K.FP.skinmax] = sc.simulation["neighbor_skin"]
        ip[K.IP.autoskin] = 1 if sc.simulation.get("neighbor_skin_auto") else 0
        fp[K.FP.vchar] = self.characteristic_velocity()
        fp[K.FP.ktratio] = sc.contact["tangential_stiffness_ratio"]
        fp[K.FP.linkn] = sc.contact["normal_stiffness"]
        fp[K.FP.etar] = sc.contact["rolling_damping"]
        fp[K.FP.maxov] = sc.simulation["max_overlap_ratio"]
        fp[K.FP.vwall] = self.wall_speed
        return ip, fp

    def characteristic_velocity(self):
        """Impact velocity used for the Hertz time and the linear stiffness: the scene's
        [contact] characteristic_velocity, else the largest of the initial speeds, the
        wall surface speeds and the free-fall speed over the domain height."""
        c = self.scene.contact["characteristic_velocity"]
        if c:
            return c
        st = self.state
        g = np.linalg.norm(self.scene.simulation["gravity"])
        h = float(np.max(st.hi - st.lo))
        v0 = (float(self.scene.max_speed) if getattr(self.scene, "distributed", False)
              else float(np.max(np.linalg.norm(st.velocity, axis=1), initial=0.0)))
        vw = 0.0
        for w in self.scene.walls:
            vw = max(vw, float(np.linalg.norm(w["velocity"])))
            if w.get("oscillation"):
                vw = max(vw, wall_surface_speed(w))
            om = float(np.linalg.norm(w["angular_velocity"]))
            if om > 0:
                vw = max(vw, om * (w.get("radius") or float(np.max(st.hi - st.lo))))
        vin = max([float(np.linalg.norm(i["velocity"])) for i in self.scene.inlets], default=0.0)
        return max(v0, vw, vin, math.sqrt(2 * g * h), 1e-3)

    def halo(self, bound=False):
        """Ghost layer width: the longest pair reach 2 r_max + reach + skin, or further when
        a coupled run's particle void fraction searches further (``ghost_reach``). ``bound``:
        with the largest skin (an adaptive skin's bound): what the cuts of the boxes, the
        neighbour ranks and the gas cells a coupled rank sees are sized for, so that they stay
        valid whatever skin the motion chooses; the ghosts sent use the skin of the moment."""
        skin = self.state.fp[K.FP.skinmax] if bound else self.state.fp[K.FP.skin]
        return 2.0 * self.rmax + max(self.reach, self.ghost_reach) + skin

    def hold_mesh_near(self, blo, bhi):
        """Hold in the mesh tables only the triangles a particle owned in the box [blo, bhi] (a
        rank's, dem.parallel) can reach until the end of the run (:func:`mesh_selection`: their
        swept boxes within the margin below). Called by the decomposition after each cut of the
        boxes, before the neighbour build that finds the candidates anew (dem.schema mtri: they
        index these tables and are never sent or saved). The margin: the largest radius with
        the heat models' reach or a radiating wall's range, the largest skin (the candidates'
        search) and once more (how far an owned particle moves out of its box before it
        migrates: half the skin), and the ghost layer's pair reach besides. Returns how many."""
        if not self.nmeshes:
            return 0
        st = self.state
        skin = float(st.fp[K.FP.skinmax])
        srange = float(K.mesh_radiation_range.py_func(st.bundles()[4]))   # (the kernels' own rule)
        margin = self.halo(bound=True) + srange * self.rmax + 2.0 * skin
        t1 = self.time + max(self.end_time - self.time, 1000.0 * self.dt)
        sel = mesh_selection(self.scene.walls, blo, bhi, margin, self.time, t1)
        self.mesh_held = mesh_tables(self.state, self.scene.walls, self.mesh_cell, sel)
        # a translating mesh's triangles were taken for [time, t1]: taken again half-way there
        moves = any(w["type"] == "mesh" and np.any(np.asarray(w["velocity"], float) != 0.0) for w in self.scene.walls)
        self.mesh_until = 0.5 * (self.time + t1) if moves else math.inf
        return self.mesh_held

    def set_step(self, step_count):
        """Set the clock to step number ``step_count`` (the time follows: step_count x dt)."""
        self.step_count = int(step_count)
        self.time = self.step_count * self.dt

    @property
    def mechanics(self):
        """False for a frozen packing (simulation.mechanics = false)."""
        return bool(self.state.ip[K.IP.mech])


def pair_tables(scene):
    """(tab[TAB.SIZE, n_mat, n_mat], the mixed material tables) of the scene's materials."""
    t = mixed_tables(scene.materials)
    nm = t["n"]
    model = CONTACT_MODELS[scene.contact["model"]]
    damping = DAMPING_MODELS[scene.contact["damping"]]
    tab = np.zeros((K.TAB.SIZE, nm, nm))
    tab[K.TAB.estar] = t["estar"]
    tab[K.TAB.gstar] = t["gstar"]
    tab[K.TAB.mu] = t["friction"]
    tab[K.TAB.mur] = t["rolling_friction"]
    # c_t / c_n of the Hertz-Mindlin law (dem.contact.hertz_mindlin), once per pair, not per contact
    tab[K.TAB.ctr] = np.sqrt(4.0 * t["gstar"] / t["estar"])
    for a in range(nm):
        for b in range(nm):
            tab[K.TAB.damp, a, b] = damping_factor(t["restitution"][a, b], model, damping)
    return np.ascontiguousarray(tab), t


def wall_surface_speed(w):
    """The fastest a wall's surface moves towards a particle (m/s, the rebuild test): its
    translation, and for a turning mesh the rotation at its farthest vertex (a plane or a
    cylinder turns within its own surface)."""
    v = float(np.linalg.norm(w["velocity"]))
    if w["type"] == "mesh":
        s = w["surface"]
        v += float(np.linalg.norm(w["angular_velocity"])) * float(
            np.max(np.linalg.norm(s.verts - w["rotation_center"], axis=1), initial=0.0))
        osc = w.get("oscillation")
        if osc:
            v += float(np.linalg.norm(osc["amplitude"])) * 2.0 * math.pi * osc["frequency"]
    return v


def swept_boxes(w, t0, t1):
    """The box (lo, hi: (n, 3) each) that each triangle of mesh wall ``w`` stays in over the
    times [t0, t1], for any of its motions: a rotation sweeps the triangle round the axis (the
    box of the cylinder segment of its farthest vertex from the axis over its axial extent), then
    the translation V t over [t0, t1] and an oscillation's amplitude either way (twice: A (sin(w t
    + phi) - sin(phi)) spans up to 2 |A|)."""
    s = w["surface"]
    tri = s.verts[s.faces]                       # (n, 3 corners, 3)
    om = np.asarray(w["angular_velocity"], float)
    if np.any(om != 0.0):
        a = om / np.linalg.norm(om)
        c = np.asarray(w["rotation_center"], float)
        rel = tri - c
        ax = rel @ a                             # (n, 3): axial coordinates of the corners
        rho = np.linalg.norm(rel - ax[..., None] * a, axis=2).max(axis=1)
        s0, s1 = ax.min(axis=1), ax.max(axis=1)
        e0, e1 = c + s0[:, None] * a, c + s1[:, None] * a
        rad = rho[:, None] * np.sqrt(np.clip(1.0 - a * a, 0.0, 1.0))
        lo, hi = np.minimum(e0, e1) - rad, np.maximum(e0, e1) + rad
    else:
        lo, hi = tri.min(axis=1), tri.max(axis=1)
    v = np.asarray(w["velocity"], float)
    lo = lo + np.minimum(v * t0, v * t1)
    hi = hi + np.maximum(v * t0, v * t1)
    osc = w.get("oscillation")
    if osc:
        amp = 2.0 * np.abs(np.asarray(osc["amplitude"], float))
        lo, hi = lo - amp, hi + amp
    return lo, hi


def mesh_selection(walls, blo, bhi, margin, t0, t1):
    """Per mesh wall, the triangles (sorted indices) whose swept box over [t0, t1]
    (:func:`swept_boxes`) comes within ``margin`` of the box [blo, bhi] (a rank's box of the
    decomposition: infinite on the domain's outer faces): all that a particle owned there can
    touch, a contact reaching no further than its radius, the heat models' reach and a wall's
    radiation range, and an owned particle no further outside its box than the skin."""
    sel = []
    lo_b = np.asarray(blo, float) - margin
    hi_b = np.asarray(bhi, float) + margin
    for w in walls:
        if w["type"] != "mesh":
            continue
        lo, hi = swept_boxes(w, t0, t1)
        keep = np.all((hi >= lo_b) & (lo <= hi_b), axis=1)
        sel.append(np.nonzero(keep)[0])
    return sel


def _subset(s, faces_kept):
    """The vertices, faces (renumbered), edge and vertex valences of the triangles
    ``faces_kept`` of surface ``s``: the valences are the whole mesh's (an edge at the subset's
    border keeps its two triangles: the contact of a sphere there is decided as on the whole
    mesh, the other triangle being kept wherever that sphere can be owned)."""
    f = s.faces[faces_kept]
    used = np.unique(f)
    ren = np.full(len(s.verts), -1, np.int64)
    ren[used] = np.arange(used.size)
    return (np.ascontiguousarray(s.verts[used]), np.ascontiguousarray(ren[f]),
            np.ascontiguousarray(s.edge_val[faces_kept]), np.ascontiguousarray(s.vert_val[used]))


def mesh_tables(st, walls, cell, select=None):
    """The Walls bundle's mesh arrays (dem.schema owner "mesh"): every mesh wall's vertices,
    faces, valences and triangle bins (cubes of ``cell``, the particles' cell size) concatenated,
    its motion and rows (dem.contact.mesh MM, MMI). ``select``: per mesh wall the triangles to
    hold (:func:`mesh_selection`: a rank's, in their order in the file), else all of them.
    Returns the number of triangles held."""
    from .contact.mesh import MM, MMI, DENSE_MAX, bin_triangles
    first, _ = W.wall_rows(walls)
    meshes = [(k, w) for k, w in enumerate(walls) if w["type"] == "mesh"]
    nm = len(meshes)
    mm = np.zeros((nm, MM.SIZE))
    mmi = np.zeros((nm, MMI.SIZE), np.int64)
    mv, mfc, mev, mvv, keys, start, items, dense = [], [], [], [], [], [], [], [np.zeros(0, np.int32)]
    nv = nt = nk = ni = nd = 0
    for m, (k, w) in enumerate(meshes):
        s = w["surface"]
        if select is None:
            verts, faces, ev, vv = s.verts, s.faces, s.edge_val, s.vert_val
            lo, c, dims, bk, bs, bi = s.bins(float(cell))
        else:
            verts, faces, ev, vv = _subset(s, select[m])
            if len(faces):
                lo, c, dims, bk, bs, bi = bin_triangles(verts, faces, float(cell))
            else:   # none near this rank: an empty grid of one cell
                lo, c, dims = np.zeros(3), float(cell), np.ones(3, np.int64)
                bk, bi, bs = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64)
        mm[m, MM.vx:MM.vx + 3] = w["velocity"]
        mm[m, MM.ox:MM.ox + 3] = w["angular_velocity"]
        mm[m, MM.cx:MM.cx + 3] = w["rotation_center"]
        mm[m, MM.lo:MM.lo + 3] = lo
        mm[m, MM.cell] = c
        osc = w.get("oscillation")
        if osc:
            mm[m, MM.ax:MM.ax + 3] = osc["amplitude"]
            mm[m, MM.osc] = 2.0 * math.pi * osc["frequency"]
            mm[m, MM.phase] = math.radians(osc["phase"])
        mmi[m, MMI.row0] = first[k]
        mmi[m, MMI.nslot] = w["slots"]
        mmi[m, MMI.dims:MMI.dims + 3] = dims
        mmi[m, MMI.k0] = nk
        mmi[m, MMI.nk] = len(bk)
        mmi[m, MMI.t0] = nt
        ncell = int(np.prod(dims))
        if ncell <= DENSE_MAX:
            mmi[m, MMI.d0] = nd
            d = np.full(ncell, -1, np.int32)
            d[bk] = np.arange(len(bk), dtype=np.int32)
            dense.append(d)
            nd += ncell
        else:
            mmi[m, MMI.d0] = -1
        mmi[m, MMI.nt] = len(faces)
        mv.append(verts)
        mfc.append(faces + nv)
        mev.append(ev)
        mvv.append(vv)
        keys.append(bk)
        start.append(bs + ni)
        items.append(bi + nt)
        nv += len(verts)
        nt += len(faces)
        nk += len(bk)
        ni += len(bi)
    cat = lambda a, dt: np.ascontiguousarray(np.concatenate(a).astype(dt))   # noqa: E731
    st.mv = np.ascontiguousarray(np.concatenate(mv).astype(float).reshape(-1, 3))
    st.mfc = np.ascontiguousarray(np.concatenate(mfc).astype(np.int64).reshape(-1, 3))
    st.mev = np.ascontiguousarray(np.concatenate(mev).astype(np.int64).reshape(-1, 3))
    st.mvv = cat(mvv, np.int64)
    st.mkeys, st.mstart, st.mitems = cat(keys, np.int64), cat(start, np.int64), cat(items, np.int64)
    st.mm, st.mmi = mm, mmi
    st.mdense = cat(dense, np.int32)
    a, b, c = (st.mv[st.mfc[:, k]] for k in range(3))
    nrm = np.cross(b - a, c - a)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]   # (no degenerate triangle: dem.contact.mesh.check_triangles)
    st.mpl = np.ascontiguousarray(np.c_[nrm, np.einsum("ij,ij->i", nrm, a)])
    st.mstamp = np.zeros(nt + 1, np.int64)
    st.mout = np.empty(nt, np.int64)
    st.mraw = np.empty((nt, 8))
    return nt


def wall_tables(walls):
    """(wf[n, WF.SIZE], wi[n, WI.SIZE]) of the scene's wall rows (one empty row without walls):
    a plane or a cylinder is one row, a mesh wall its ``slots`` rows (dem.contact.walls.wall_rows)."""
    first, owner = W.wall_rows(walls)
    nw = owner.size
    wf = np.zeros((max(nw, 1), W.WF.SIZE))
    wi = np.zeros((max(nw, 1), W.WI.SIZE), np.int64)
    wi[:, W.WI.mesh] = -1
    m = 0
    for row, kw in enumerate(owner):
        k, w = row, walls[kw]
        wf[k, W.WF.px:W.WF.px + 3] = w["point"]
        wf[k, W.WF.vx:W.WF.vx + 3] = w["velocity"]
        wf[k, W.WF.ox:W.WF.ox + 3] = w["angular_velocity"]
        wf[k, W.WF.cx:W.WF.cx + 3] = w["rotation_center"]
        wi[k, W.WI.mat] = w["material"]
        if w["type"] == "mesh":
            wi[k, W.WI.type] = W.MESH
            wi[k, W.WI.mesh] = m
            if row == first[kw] + w["slots"] - 1:
                m += 1
        elif w["type"] == "plane":
            wi[k, W.WI.type] = W.PLANE
            wf[k, W.WF.nx:W.WF.nx + 3] = w["normal"]
            wf[k, W.WF.ux:W.WF.ux + 3] = w["u_axis"]
            ext = w["extent"]
            wf[k, W.WF.eu] = math.inf if ext is None else ext[0]
            wf[k, W.WF.ev] = math.inf if ext is None else ext[1]
        else:
            wi[k, W.WI.type] = W.CYLINDER
            wf[k, W.WF.nx:W.WF.nx + 3] = w["axis"]
            wf[k, W.WF.rad] = w["radius"]
            wf[k, W.WF.eu] = w["length"] / 2
            wf[k, W.WF.side] = 1.0 if w["inside"] else -1.0
    return wf, wi
