"""Cost of the [averaging] particle columns per coupling step, on the main case's set-up
(3000 beads, 600 cells, smoothed void fraction), against the whole prepare() of a step.

    python3 benchmarks/averaging_cost.py    (docs/benchmarks.md, "What the time averages cost")
"""
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from coupling.case import load_case, mesh_in_tmp
from coupling.interface import CouplingInterface
from coupling.averaging import particle_columns
case = load_case(Path(__file__).resolve().parents[1] / "openfoam_cases" / "fluidized_bed_heating")
tmp, mesh = mesh_in_tmp(case.dir)
iface = CouplingInterface.for_case(case, mesh)
iface.initial_void_fraction()
n = mesh.n_cells
fluid = dict(U=np.zeros((n, 3)) + [0, 0, 2.0], T=np.full(n, 373.15), gradp=np.zeros((n, 3)), p=np.zeros(n))
iface.prepare(fluid, case.dt_cfd)
pw, _ = iface._stencil()
st = case.sim.state
m = st.n_owned
args = (pw, st.radius[:m], st.velocity[:m], st.temperature[:m], iface.V, iface.cells)
particle_columns(*args)
for rep in range(3):
    t0 = time.perf_counter()
    K = 200
    for _ in range(K):
        particle_columns(*args)
    tc = (time.perf_counter() - t0) / K
    t0 = time.perf_counter()
    K2 = 50
    for _ in range(K2):
        iface._map_cache = None
        iface.prepare(fluid, case.dt_cfd)
    tp = (time.perf_counter() - t0) / K2
    print(f"particle_columns {tc*1e6:.0f} us per step; prepare (locate, stencil, forces, exchange terms) {tp*1e3:.2f} ms; ratio {tc/tp:.3f}")
import shutil  # noqa: E402
shutil.rmtree(tmp, ignore_errors=True)
