"""Set-up memory per rank (issue 26, item 3): a packing file of N beads read by M ranks.

    python benchmarks/setup_memory.py write DIR [N]      # DIR/bed.csv, bed.npz and the scenes
    mpirun -np M python benchmarks/setup_memory.py measure DIR/csv.toml

``measure`` builds the Simulation (scene read, particles distributed, first neighbour build)
and prints, per rank, the particle rows it read and held during the set-up, the rows it owns,
and its peak resident memory (ru_maxrss) after the set-up. docs/scaling.md has the figures.
"""
import os
import resource
import sys

import numpy as np

SCENE = """[simulation]
time_step = 1e-5
end_time = 1e-4
[domain]
min = [0.0, 0.0, 0.0]
max = [{L}, {L}, {H}]
[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5
[[particles]]
material = "glass"
file = "{file}"
"""


def write(d, n):
    k = int(round(n ** (1 / 3)))
    g = np.stack(np.meshgrid(np.arange(k), np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 3)
    x = 0.0015 + 0.0023 * g
    r = np.full(len(g), 0.001)
    os.makedirs(d, exist_ok=True)
    np.savez(os.path.join(d, "bed.npz"), position=x, radius=r)
    with open(os.path.join(d, "bed.csv"), "w") as fh:
        fh.write("x,y,z,radius\n")
        np.savetxt(fh, np.concatenate([x, r[:, None]], 1), delimiter=",", fmt="%.17g")
    L = 0.003 + 0.0023 * k
    for f in ("csv", "npz"):
        with open(os.path.join(d, f"{f}.toml"), "w") as fh:
            fh.write(SCENE.format(L=L, H=L, file=f"bed.{f}"))
    print(f"{len(g)} beads in {d}")


def measure(scene):
    from dem.simulation import Simulation
    sim = Simulation.from_file(scene)
    rows = getattr(sim.scene, "setup_rows", None) or dict(read=len(sim.scene.radius), held=len(sim.scene.radius))
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    line = (f"rank {sim.par.rank if sim.par else 0}: read {rows['read']} rows, held {rows['held']}, "
            f"owns {sim.state.n_owned} of {sim.n_particles}, peak RSS {rss:.0f} MiB")
    lines = sim.par.comm.gather(line, root=0) if sim.par else [line]
    if sim.is_root:
        print("\n".join(lines))


if __name__ == "__main__":
    if sys.argv[1] == "write":
        write(sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 216000)
    else:
        measure(sys.argv[2])
