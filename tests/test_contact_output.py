"""[output] contacts: the contact network (contacts.pvd: a line per touching pair with its elastic
normal force, overlap and heat flow) and per particle the contact force and the coordination
number, through `dem run` on a lattice whose contacts are known exactly."""
import math
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
R = 1e-3
E, NU = 1e7, 0.3
DELTA = 2e-5          # every contact's overlap: the lattice pitch 2 R - DELTA, the floor R - DELTA below
DT = 0.01             # the thermal step (a frozen bed, explicit Euler)


def _scene(tmp_path, ranks=1):
    g = np.arange(3) * (2 * R - DELTA)
    groups = ""
    for k, z in enumerate(g):
        pos = [[float(x), float(y), float(z + R - DELTA)] for y in g for x in g]
        groups += f"""
[[particles]]
material = "p"
radius = {R}
positions = {pos}
temperature = {300.0 + 20.0 * k}
"""
    f = tmp_path / "lattice.toml"
    f.write_text(f"""
[simulation]
time_step = 1e-5
end_time = {2 * DT}
mechanics = false
gravity = [0.0, 0.0, 0.0]
output_interval = {DT}

[domain]
min = [-0.003, -0.003, -0.001]
max = [0.007, 0.007, 0.007]

[[materials]]
name = "p"
density = 2500.0
youngs_modulus = {E}
poisson_ratio = {NU}
restitution = 0.5
friction = 0.3
thermal_conductivity = 1.0
heat_capacity = 840.0
{groups}
[[walls]]
type = "plane"
name = "floor"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "p"
thermal = {{ condition = "fixed_temperature", temperature = 400.0 }}

[thermal]
direct = "batchelor_obrien"
integrator = "euler"
time_step = {DT}

[output]
contacts = true
""")
    return f


def _run(f, out, ranks=1):
    env = dict(os.environ, PYTHONPATH=ROOT, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
    cmd = [sys.executable, "-m", "dem", "run", str(f), "--out", str(out), "--quiet"]
    if ranks > 1:
        cmd = ["mpirun", "-np", str(ranks)] + cmd
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)
    assert p.returncode == 0, p.stderr
    return out


def _network(out, index):
    """Lines and cell data of contacts.pvd's frame at step ``index`` (a .vtu, or a .pvtu's pieces)."""
    import meshio
    base = out / "vtk" / f"contacts_{index:06d}"
    parts = [base.with_suffix(".vtu")] if base.with_suffix(".vtu").exists() else \
        sorted((out / "vtk").glob(f"contacts_{index:06d}_p*.vtu"))
    assert parts, list((out / "vtk").iterdir())
    data = {}
    for p in parts:
        m = meshio.read(p)
        for k, v in m.cell_data.items():
            data.setdefault(k, []).append(np.concatenate(v))
    return {k: np.concatenate(v) for k, v in data.items()}


def test_the_network_and_the_coordination_of_a_pressed_lattice(tmp_path):
    """3 x 3 x 3 spheres pressed DELTA into each other and the bottom layer into a floor:
    54 lines, each pair once, each with the Hertz force 4/3 E* sqrt(R/2) DELTA^3/2 (1e-12) and
    the overlap DELTA (1e-12 of it); every particle's coordination number its lattice
    neighbours plus the floor for the bottom layer (exactly); the contact forces sum to the
    floor's Hertz force on the 9 bottom spheres, 4/3 E* sqrt(R) DELTA^3/2 each (1e-9), the pairs'
    forces cancelling; and the lines' heat flows, the pairs' conduction at the temperatures of
    the output, are what the next step exchanges: their |sum| times the step is history.csv's
    E_direct increment (to its 12 digits)."""
    from dem.final import read as read_final
    out = _run(_scene(tmp_path), tmp_path / "out")
    fin = read_final(out / "final.npz")
    pos = fin["position"]
    ijk = np.rint((pos - [0.0, 0.0, R - DELTA]) / (2 * R - DELTA)).astype(int)
    lattice = sum(((ijk[:, a] > 0).astype(int) + (ijk[:, a] < 2).astype(int)) for a in range(3))
    assert np.array_equal(fin["coordination"].astype(int), lattice + (ijk[:, 2] == 0))
    estar = E / (2 * (1 - NU ** 2))
    net = _network(out, 0)
    assert net["normal_force"].size == 54
    pairs = set(zip(net["id_a"].astype(int), net["id_b"].astype(int)))
    assert len(pairs) == 54 and all(a != b for a, b in pairs)
    assert net["normal_force"] == pytest.approx(np.full(54, 4 / 3 * estar * math.sqrt(R / 2) * DELTA ** 1.5),
                                                rel=1e-12)
    assert net["overlap"] == pytest.approx(np.full(54, DELTA), rel=1e-9)
    fwall = 4 / 3 * estar * math.sqrt(R) * DELTA ** 1.5
    cf = fin["contact_force"]
    assert cf[:, 2].sum() == pytest.approx(9 * fwall, rel=1e-9)
    assert np.abs(cf[:, :2].sum(axis=0)).max() <= 1e-9 * fwall
    assert np.all(cf[ijk[:, 2] == 0, 2] > 0.0)
    h = np.genfromtxt(out / "history.csv", delimiter=",", names=True)
    net1 = _network(out, 1)
    assert np.abs(net1["heat_flow"]).sum() > 0.0
    de = h["E_direct"][2] - h["E_direct"][1]
    assert np.abs(net1["heat_flow"]).sum() * DT == pytest.approx(de, rel=1e-9)


def test_the_network_on_two_ranks_is_the_serial_one(tmp_path):
    """The same lattice on 2 MPI ranks: contacts.pvd's frame is a .pvtu of pieces, each pair in
    exactly one piece (54 in all, the same pairs) with the serial forces and heat flows (1e-12)."""
    import shutil
    if shutil.which("mpirun") is None:
        pytest.skip("needs Open MPI (mpirun)")
    f = _scene(tmp_path)
    a = _network(_run(f, tmp_path / "np1"), 1)
    out2 = _run(f, tmp_path / "np2", ranks=2)
    assert (out2 / "vtk" / "contacts_000001.pvtu").exists()
    b = _network(out2, 1)
    key = lambda d: np.lexsort((d["id_b"], d["id_a"]))   # noqa: E731
    ka, kb = key(a), key(b)
    assert b["normal_force"].size == 54
    assert np.array_equal(a["id_a"][ka], b["id_a"][kb]) and np.array_equal(a["id_b"][ka], b["id_b"][kb])
    assert b["normal_force"][kb] == pytest.approx(a["normal_force"][ka], rel=1e-12)
    assert b["heat_flow"][kb] == pytest.approx(a["heat_flow"][ka], rel=1e-12, abs=1e-15)
