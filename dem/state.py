"""The run's arrays, as declared in dem.schema (structure of arrays, float64, C-contiguous).

Particles carry global ids. Rows [0, n_owned) are owned by this rank; rows
[n_owned, n_owned + n_ghost) are ghosts (copies of neighbours' particles, filled by the
parallel layer); kernels integrate owned rows only. A serial run has no ghosts.

Every array of dem.schema.FIELDS is an attribute of the same name; an array a scene does not
enable is the empty array of its row (zero rows, same dtype and axes). The kernels get the
arrays as the named bundles of dem.schema (:meth:`bundles`).
"""
import numpy as np

from . import schema as S


def sphere_masses(radius, density):
    """(mass, 1 / mass, 1 / (2/5 m R^2)) of spheres of the given radii and densities: the rows a
    scene's particles start with (State) and an inlet's get (dem.flow)."""
    mass = 4.0 / 3.0 * np.pi * radius ** 3 * density
    return mass, 1.0 / mass, 1.0 / (0.4 * mass * radius ** 2)


class State:
    def __init__(self, ids, position, velocity, angular_velocity, radius, material, group, densities,
                 walls=0):
        n = len(ids)
        self.n_owned = n
        self.n_ghost = 0
        self.walls = max(int(walls), 1)
        self.features = {}
        for f in S.FIELDS:  # every array declared, disabled until allocated
            setattr(self, f.name, f.empty())
        self.id = np.ascontiguousarray(ids, np.int64)
        self.position = np.ascontiguousarray(position, float).reshape(n, 3).copy()
        self.velocity = np.ascontiguousarray(velocity, float).reshape(n, 3).copy()
        self.angular_velocity = np.ascontiguousarray(angular_velocity, float).reshape(n, 3).copy()
        self.radius = np.ascontiguousarray(radius, float).copy()
        self.material = np.ascontiguousarray(material, np.int32)
        self.group = np.ascontiguousarray(group, np.int32)
        self.mass, self.inv_mass, self.inv_inertia = sphere_masses(self.radius,
                                                                   np.asarray(densities, float)[self.material])
        self.allocate()
        self.x_build = self.position.copy()

    @property
    def n(self):
        return self.n_owned + self.n_ghost

    @property
    def thermal(self):
        return bool(self.features.get("heat"))

    def enable(self, **features):
        """Switch features on or off (dem.schema.FEATURES) and allocate what they need."""
        self.features.update(features)
        self.allocate()

    def allocate(self):
        """Zeros for every enabled per-particle array not yet of n rows; the disabled ones
        empty. Pair arrays are sized by the neighbour build, not here."""
        n = self.n
        for f in S.FIELDS:
            if f.owner != "particle":
                continue
            a = getattr(self, f.name)
            if not S.enabled(f, self.features):
                if a.shape[0]:
                    setattr(self, f.name, f.empty())
            elif a.shape != f.shape(n, self.walls):
                setattr(self, f.name, np.zeros(f.shape(n, self.walls), f.dtype))

    def enable_thermal(self, temperature, heat_capacity_per_material):
        self.enable(heat=True)
        self.temperature = np.ascontiguousarray(temperature, float).copy()
        cp = np.asarray(heat_capacity_per_material, float)[self.material]
        self.inv_heat_capacity = 1.0 / (self.mass * cp)

    def fields(self, owner="particle", **flags):
        """Names of the enabled arrays of ``owner`` whose flags match (e.g. sort=True)."""
        return [f.name for f in S.FIELDS if f.owner == owner and S.enabled(f, self.features)
                and all(bool(getattr(f, k)) == v for k, v in flags.items())]

    def real_radius(self, n):
        """The radii of the real particles of rows [0, n): r / cg for a parcel (dem.schema cg),
        r otherwise."""
        r = self.radius[:n]
        return r / self.cg[:n] if self.cg.shape[0] else r

    def heat_totals(self):
        """Copies of the run's heat totals: the checkpointed wall and parameter arrays of
        dem.schema (per mechanism, per wall and path)."""
        return {f.name: getattr(self, f.name).copy() for f in S.FIELDS
                if f.owner in ("wall", "param") and f.checkpoint and S.enabled(f, self.features)}

    def restore_heat_totals(self, saved):
        for k, v in saved.items():
            getattr(self, k)[:] = v

    def permute(self, perm):
        """Reorder the particles (spatial sort): every sorted per-particle array follows; the
        pair arrays follow with their neighbour indices renumbered."""
        inv = np.empty_like(perm)
        inv[perm] = np.arange(perm.size)
        for f in S.FIELDS:
            if f.owner not in ("particle", "pair") or not f.sort:
                continue
            a = getattr(self, f.name)
            if a.shape[0] == 0:
                continue
            if not f.scratch:  # scratch: rewritten before it is read
                setattr(self, f.name, np.ascontiguousarray(a[perm]))
        nb, nnb = self.nb, self.nnb
        mask = np.arange(nb.shape[1])[None, :] < nnb[:, None]
        self.nb = np.ascontiguousarray(np.where(mask, inv[np.where(mask, nb, 0)], 0).astype(np.int32))

    def __setattr__(self, name, value):
        if name in S.BY_NAME:  # a declared array replaced: the bundles are made again
            self.__dict__["_bundles"] = None
        if name in ("nb", "nnb") and self.__dict__.get("xcnt") is not None and self.xcnt.shape[0] > 0:
            self.xcnt[S.XC.nblk] = 0  # another neighbour list: the pairs across blocks are counted again
        object.__setattr__(self, name, value)

    def bundles(self):
        """(Particles, Pairs, Walls, Tables, Params) over the current arrays (kept until an
        array is replaced: an MPI step asks for them several times)."""
        b = self.__dict__.get("_bundles")
        if b is None:
            b = tuple(B(*[getattr(self, f.name) for f in S.bundle_fields(owner)])
                      for B, owner in ((S.Particles, "particle"), (S.Pairs, "pair"), (S.Walls, "wall"),
                                       (S.Tables, "table"), (S.Params, "param")))
            self.__dict__["_bundles"] = b
        return b

    def kinetic_energy(self):
        n = self.n_owned
        et = 0.5 * np.sum(self.mass[:n] * np.einsum("ij,ij->i", self.velocity[:n], self.velocity[:n]))
        er = 0.5 * np.sum(np.einsum("ij,ij->i", self.angular_velocity[:n], self.angular_velocity[:n])
                          / self.inv_inertia[:n])
        return float(et), float(er)

    def memory_bytes(self, owner="particle"):
        return sum(getattr(self, f).nbytes for f in self.fields(owner))
