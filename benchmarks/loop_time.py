"""Loop time of a shared bed (10k, or 50k) in one source tree (for comparing two trees run alternately):

    python benchmarks/loop_time.py <tree> heat|noheat <steps> [10k|50k]

Times ``sim.run`` after ``warmup`` (compile or cache load excluded) and prints "loop <s> s".
"""
import os, sys, time
root = sys.argv[1]; heat = sys.argv[2] == "heat"; steps = int(sys.argv[3])
size = sys.argv[4] if len(sys.argv) > 4 else "10k"
sys.path.insert(0, root)
from dem import Simulation
sim = Simulation.from_file(os.path.join(root, "benchmarks", f"shared_bed{'_heat' if heat else ''}_{size}.toml"))
sim.warmup()
t0 = time.perf_counter()
sim.run(end_time=steps * sim.dt, progress=False)
print(f"loop {time.perf_counter()-t0:.3f} s")
