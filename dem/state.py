"""Structure-of-arrays particle state (float64, C-contiguous).

Particles carry global ids. Rows [0, n_owned) are owned by this rank; rows
[n_owned, n_owned + n_ghost) are ghosts (copies of neighbours' particles, filled by the
parallel layer); kernels integrate owned rows only. A serial run has no ghosts.
"""
import numpy as np

# per-particle arrays that move with a particle (permutation, checkpoint, migration)
VEC_FIELDS = ("position", "velocity", "angular_velocity", "force", "torque", "x_build")
SCALAR_FIELDS = ("radius", "mass", "inv_mass", "inv_inertia")
INT_FIELDS = ("id", "material", "group")
THERMAL_FIELDS = ("temperature", "heat_rate", "inv_heat_capacity")


class State:
    def __init__(self, ids, position, velocity, angular_velocity, radius, material, group, densities):
        n = len(ids)
        self.n_owned = n
        self.n_ghost = 0
        self.id = np.ascontiguousarray(ids, np.int64)
        self.position = np.ascontiguousarray(position, float).reshape(n, 3).copy()
        self.velocity = np.ascontiguousarray(velocity, float).reshape(n, 3).copy()
        self.angular_velocity = np.ascontiguousarray(angular_velocity, float).reshape(n, 3).copy()
        self.radius = np.ascontiguousarray(radius, float).copy()
        self.material = np.ascontiguousarray(material, np.int32)
        self.group = np.ascontiguousarray(group, np.int32)
        rho = np.asarray(densities, float)[self.material]
        self.mass = 4.0 / 3.0 * np.pi * self.radius ** 3 * rho
        self.inv_mass = 1.0 / self.mass
        self.inv_inertia = 1.0 / (0.4 * self.mass * self.radius ** 2)
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
        self.x_build = self.position.copy()
        self.thermal = False

    @property
    def n(self):
        return self.n_owned + self.n_ghost

    def enable_thermal(self, temperature, heat_capacity_per_material):
        n = self.n
        self.thermal = True
        self.temperature = np.ascontiguousarray(temperature, float).copy()
        self.heat_rate = np.zeros(n)
        cp = np.asarray(heat_capacity_per_material, float)[self.material]
        self.inv_heat_capacity = 1.0 / (self.mass * cp)

    def fields(self):
        f = list(VEC_FIELDS + SCALAR_FIELDS + INT_FIELDS)
        if self.thermal:
            f += list(THERMAL_FIELDS)
        return f

    def permute(self, perm):
        for name in self.fields():
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[perm]))

    def kinetic_energy(self):
        n = self.n_owned
        et = 0.5 * np.sum(self.mass[:n] * np.einsum("ij,ij->i", self.velocity[:n], self.velocity[:n]))
        er = 0.5 * np.sum(np.einsum("ij,ij->i", self.angular_velocity[:n], self.angular_velocity[:n])
                          / self.inv_inertia[:n])
        return float(et), float(er)

    def memory_bytes(self):
        return sum(getattr(self, f).nbytes for f in self.fields())
