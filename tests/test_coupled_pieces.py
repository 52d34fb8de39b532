"""The set-up of a coupled run by gas pieces (coupling.pieces): with gas_processes = N > 1 the
case is decomposed first and every DEM rank reads only the processor meshes around its box
and those holding its cells; no rank reads the whole mesh. Run as a user runs it:
``mpirun -np M python -m coupling.run run CASE``.

What is asserted, and why:

* what each rank read at set-up (timings.json): pieces whose cells are fewer than the mesh's,
  and every cell owned exactly once (owned cells sum to the mesh);
* the check report the run prints equals ``coupling check CASE`` (one process, the whole mesh):
  the mesh values come from reductions over the owned cells (min, max and sums of counts, so
  the numbers are the same, not merely close);
* each processor's 0/eps, written from the owners' values, equals byte for byte what
  decomposePar writes from the whole 0/eps holding the same values;
* a restart continues the run by pieces and ends where the uninterrupted run ends, to the
  round-off bound of the (3, 2) restart of tests/test_coupled_m2m.py (1e-13 m, 1e-10 m/s,
  1e-10 K).
"""
from __future__ import annotations

import filecmp
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from test_coupled_m2m import _env, _is_time, assert_close, case_with, coupled, final  # noqa: E402


def _report(text: str) -> list:
    """The check report's lines (from the first value to the verdict), but the DEM's
    coordination number: the contact count of dem.simulation.check, which on this bed differs
    between one process and two ranks (dem/ is untouched here; not a value of the mesh)."""
    lines = text.splitlines()
    i = next(k for k, x in enumerate(lines) if x.startswith("coupled case"))
    j = next(k for k, x in enumerate(lines) if x.strip().startswith("verdict"))
    return [x for x in lines[i + 1:j + 1] if not x.strip().startswith("coordination_number")]


def test_two_dem_ranks_on_three_gas_pieces(solver, tmp_path):
    from coupling import foam_case as fc
    # the coarse-grained bed (6,000 cells): the DEM boxes are cut across x (the bed is wider
    # than tall), the gas in three slabs across x, so each box and its view lie on part of the
    # pieces (with fewer pieces than boxes, a box always straddles two pieces)
    case = case_with(tmp_path, "fluidized_bed_cg", 3, tag="_pieces")
    d = case / "system" / "decomposeParDict"
    d.write_text(d.read_text().replace("n           (1 1 2);", "n           (3 1 1);"))
    c = case / "system" / "controlDict"
    c.write_text(c.read_text().replace("writeInterval   400;", "writeInterval   2;"))
    out = tmp_path / "out"
    p = coupled(2, case, out, "--end-time", "0.0015")   # 6 coupling steps: restart points at 2, 4, 6
    ranks = json.loads((out / "timings.json").read_text())["ranks"]
    addr = fc.cell_proc_addressing(out)
    n = sum(a.size for a in addr)
    assert len(addr) == 3 and sum(r["owned_cells"] for r in ranks) == n
    for r in ranks:
        read = r["setup_pieces_read"]
        assert read and r["setup_cells_read"] == sum(addr[int(q[9:])].size for q in read)
        assert r["setup_cells_read"] < n, r
        assert r["owned_cells"] <= r["local_cells"] <= r["setup_cells_read"]
    # every piece went through the table exactly once (round-robin over the ranks)
    assert sorted(k for r in ranks for k in r["table_pieces_read"]) == [0, 1, 2]
    # the printed checks equal those of `coupling check` on the whole mesh
    chk = subprocess.run([sys.executable, "-m", "coupling.run", "check", str(case)], capture_output=True, text=True,
                         env=_env(), timeout=900, cwd=str(ROOT))
    assert chk.returncode == 0, chk.stderr[-2000:]
    assert _report(p.stdout) == _report(chk.stdout)
    # 0/eps of each processor: what decomposePar writes from the same values in the whole 0/eps
    eps = np.zeros(n)
    seen = np.zeros(n, int)
    for k, a in enumerate(addr):
        eps[a] = fc.read_internal_field(out / f"processor{k}" / "0" / "eps", a.size)
        seen[a] += 1
    assert np.all(seen == 1) and eps.min() < 0.9 and eps.max() == 1.0   # the bed and the freeboard
    ref = tmp_path / "decomposed"
    for sub in ("0", "constant", "system"):
        shutil.copytree(out / sub, ref / sub, ignore=shutil.ignore_patterns("processor*"))
    fc.write_eps(ref, eps)
    fc.decompose(ref, 3)
    for k in range(3):
        a, b = out / f"processor{k}" / "0" / "eps", ref / f"processor{k}" / "0" / "eps"
        assert filecmp.cmp(a, b, shallow=False), k
    # continue from step 4 (the later gas times removed) by pieces: the same end
    a = dict(final(out))
    for d in [out, *out.glob("processor*")]:
        for t in d.iterdir():
            if t.is_dir() and _is_time(t.name) and float(t.name) > 0.00101:
                shutil.rmtree(t)
    coupled(2, case, out, "--restart", "--end-time", "0.0015")
    ranks2 = json.loads((out / "timings.json").read_text())["ranks"]
    assert all(r["setup_cells_read"] < n for r in ranks2), ranks2
    assert_close(a, final(out), 1e-13, 1e-10, 1e-10)
    # a damaged piece (cut short): every rank stops at set-up with one line naming the rank
    # that read it and the file, exit 2, before the solver starts
    owner = out / "processor2" / "constant" / "polyMesh" / "owner"
    text = owner.read_text()
    owner.write_text(text[:len(text) // 2])
    q = coupled(2, case, out, "--restart", "--end-time", "0.002", check=False)
    assert q.returncode == 2, q.stdout[-2000:] + q.stderr[-2000:]
    lines = [x for x in q.stderr.splitlines() if x.startswith("coupling: error:")]
    assert len(lines) == 1 and "DEM rank 0" in lines[0] and str(owner) in lines[0], q.stderr[-2000:]
    assert "Traceback" not in q.stderr
