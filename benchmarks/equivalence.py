"""Results before and after a restructuring: every example's history.csv and final state, the
shared-scene temperatures, and the 2-rank MPI path, written as a fingerprint file or compared
with one.

    python benchmarks/equivalence.py --save before.json          # on the old code
    python benchmarks/equivalence.py --compare before.json       # on the new code

For each run the fingerprint holds every history.csv value (as the exact float), a sha256 of
every final array, and those arrays' values, so the comparison can say "bitwise identical"
or give the largest difference per run: over each history column's and each final array's
largest magnitude (what decides), and element by element (for information: an element near
zero, e.g. a gas velocity at a wall, makes it large for round-off alone). Exit status 1 when a
run differs by more than --rtol (default 1e-12: round-off of a reordered sum, nothing more).
``--threads N`` runs the new code on N threads per process: another order of the sums, so
round-off amplified by collisions (a bubbling bed amplifies it fastest); the examples (fewer
than 2 x 1,024 particles: one block of rows) stay bitwise.

Runs (about 4 minutes on 2 cores): the three examples to their end time, the shared 10k bed
with heat for 2,000 steps (mean temperatures of the hot and cold halves), and
tests/scenes/par_settle.toml on 2 MPI ranks (the parallel step). The coupled main case
(``coupling run openfoam_cases/fluidized_bed_heating --end-time 0.05``: 100 coupling steps with
thermoDemFoam, about a minute) is fingerprinted by its final.npz, history.csv, coupling.csv
(without the wall-clock column) and the gas fields of the last time folder (U, T, p, eps,
...: a sha256 of each file and its internal field's values). ``--only dem|coupled`` runs one
part alone (the coupled part needs OpenFOAM and the thermoDemFoam build of scripts/setup.sh).
"""
import argparse
import csv
import glob
import hashlib
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

# the tree under test: this file's, or the current folder's when the file was copied out of a
# tree (to fingerprint an older checkout with this version: cd OLD && python /tmp/equivalence.py)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isdir(os.path.join(ROOT, "dem")):
    ROOT = os.getcwd()
HERE = os.path.join(ROOT, "benchmarks")
sys.path.insert(0, ROOT)


def _history(path):
    with open(path) as fh:
        rows = list(csv.reader(fh))
    return rows[0], [[float(v) for v in r] for r in rows[1:]]


def _fingerprint(out):
    cols, rows = _history(os.path.join(out, "history.csv"))
    from dem.final import read as read_final   # an MPI run's final.npz: a manifest and its pieces
    z = read_final(os.path.join(out, "final.npz"))
    arrays = {k: np.asarray(z[k]) for k in sorted(z.files)}
    return dict(columns=cols, history=rows,
                sha={k: hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() for k, a in arrays.items()},
                final={k: np.asarray(a, float).ravel().tolist() for k, a in arrays.items()})


THREADS = ["--threads", "1"]   # (main's --threads) the threads of each process of the new runs


def _dem_run(args, out, mpi=0):
    cmd = [sys.executable, "-m", "dem", "run"] + args + ["--out", out, "--quiet"] + THREADS
    if mpi:
        cmd = ["mpirun", "--oversubscribe", "-np", str(mpi)] + (["--bind-to", "none"] if THREADS[1:] not in (
            [], ["1"]) else []) + cmd  # (mpirun binds each rank to one core: more threads need it unbound)
    env = dict(os.environ, PYTHONPATH=ROOT, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1")
    subprocess.run(cmd, check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)


COUPLED_CASE = "fluidized_bed_heating"
COUPLED_END_TIME = "0.05"
GAS_FIELDS = ("U", "T", "p", "p_rgh", "eps", "alpha", "Ksl")


def _table(path, drop=()):
    """A CSV file as (columns, rows of exact floats) without the columns in ``drop``."""
    cols, rows = _history(path)
    keep = [i for i, c in enumerate(cols) if c not in drop]
    return [cols[i] for i in keep], [[r[i] for i in keep] for r in rows]


def _gas_fields(out):
    """sha256 of every gas field file of the last time folder and its internal field's values."""
    from coupling.foam_case import read_internal_field
    times = sorted((float(p.name), p.name) for p in os.scandir(out) if p.is_dir() and _is_time(p.name))
    last = os.path.join(out, times[-1][1])
    sha, values = {}, {}
    for name in GAS_FIELDS:
        path = os.path.join(last, name)
        if not os.path.isfile(path):
            continue
        with open(path, "rb") as fh:
            sha[f"gas_{name}"] = hashlib.sha256(fh.read()).hexdigest()
        values[f"gas_{name}"] = np.asarray(read_internal_field(path), float).ravel().tolist()
    return times[-1][1], sha, values


def _is_time(name):
    try:
        return float(name) > 0
    except ValueError:
        return False


def coupled():
    """The coupled main case to COUPLED_END_TIME: one fingerprint (history = coupling.csv rows)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, COUPLED_CASE)
        env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
        subprocess.run([sys.executable, "-m", "coupling.run", "run", os.path.join(ROOT, "openfoam_cases", COUPLED_CASE),
                        "--out", out, "--end-time", COUPLED_END_TIME, "--quiet"] + THREADS,
                       check=True, env=env, cwd=ROOT, stdout=subprocess.DEVNULL)
        res = _fingerprint(out)
        ccols, crows = _table(os.path.join(out, "coupling.csv"), drop=("wall",))
        res["columns"] = res["columns"] + ccols
        res["history"] = res["history"] + crows
        last, sha, values = _gas_fields(out)
        res["sha"].update(sha)
        res["final"].update(values)
    name = f"{COUPLED_CASE} (coupled, to {COUPLED_END_TIME} s)"
    print(f"{name}: {len(crows)} coupling.csv rows, gas fields of t = {last}: {sorted(sha)}", flush=True)
    return {name: res}


def collect(quick=False, only=None):
    res = {}
    if only != "dem":
        res.update(coupled())
    if only == "coupled":
        return res
    with tempfile.TemporaryDirectory() as tmp:
        for path in sorted(glob.glob(os.path.join(ROOT, "examples", "*.toml"))):
            name = os.path.basename(path)
            out = os.path.join(tmp, name)
            extra = ["--end-time", "0.05"] if quick and "packed" not in name else []
            _dem_run([path] + extra, out)
            res[name] = _fingerprint(out)
            print(f"{name}: {len(res[name]['history'])} history rows", flush=True)
        par = os.path.join(ROOT, "tests", "scenes", "par_settle.toml")
        out = os.path.join(tmp, "par_settle_2ranks")
        _dem_run([par], out, mpi=2)
        res["par_settle.toml (2 ranks)"] = _fingerprint(out)
        print("par_settle.toml on 2 ranks: done", flush=True)
    from dem import Simulation
    sim = Simulation.from_file(os.path.join(HERE, "shared_bed_heat_10k.toml"))
    if THREADS:
        sim.set_threads(int(THREADS[1]))
    steps = 500 if quick else 2000
    sim.run(end_time=steps * sim.dt, progress=False)
    T = sim.state.temperature[:sim.state.n_owned]
    x = sim.state.position[:sim.state.n_owned, 0]
    xm = 0.5 * (sim.state.lo[0] + sim.state.hi[0])
    order = np.argsort(sim.state.id[:sim.state.n_owned])
    res["shared_bed_heat_10k"] = dict(columns=[], history=[[float(T[x < xm].mean()), float(T[x >= xm].mean())]],
                                      sha={"temperature": hashlib.sha256(T[order].tobytes()).hexdigest()},
                                      final={"temperature": T[order].tolist()})
    print(f"shared_bed_heat_10k ({steps} steps): T halves {res['shared_bed_heat_10k']['history'][0]}")
    return res


def _rel(a, b, scaled=False):
    """Largest relative difference, element by element; ``scaled``: the largest difference over
    the arrays' largest magnitude (round-off of the sums that make them; an element near zero,
    e.g. a gas velocity component at a wall, does not inflate it)."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    if a.shape != b.shape:
        return np.inf
    if a.size == 0:
        return 0.0
    if scaled:
        top = max(float(np.max(np.abs(a))), float(np.max(np.abs(b))))
        return float(np.max(np.abs(a - b))) / top if top > 0 else 0.0
    scale = np.maximum(np.abs(a), np.abs(b))
    scale = np.where(scale > 0, scale, 1.0)
    return float(np.max(np.abs(a - b) / np.maximum(scale, np.max(np.abs(a)) * 1e-300 + 1e-300)))


def compare(ref, new, rtol, only=None):
    """Every run of ``ref`` (with ``only``: those of ``ref`` this run made) against ``new``."""
    worst = 0.0
    ok = True
    for name in (n for n in ref if not only or n in new):
        if name not in new:
            print(f"{name}: missing in the new run")
            ok = False
            continue
        r, n = ref[name], new[name]
        if r["sha"] == n["sha"] and r["history"] == n["history"]:
            print(f"{name}: bitwise identical (history.csv and every final array)")
            continue
        dh = max((_rel(a, b) for a, b in zip(r["history"], n["history"])), default=0.0)
        if len(r["history"]) != len(n["history"]):
            dh = np.inf
        df = max((_rel(r["final"][k], n["final"].get(k, [])) for k in r["final"]), default=0.0)
        cols = [list(c) for c in zip(*r["history"])] if r["history"] and len(r["history"]) == len(n["history"]) else []
        ncols = [list(c) for c in zip(*n["history"])] if cols else []
        sh = max((_rel(a, b, scaled=True) for a, b in zip(cols, ncols)), default=0.0 if cols or not r["history"] else np.inf)
        sf = max((_rel(r["final"][k], n["final"].get(k, []), scaled=True) for k in r["final"]), default=0.0)
        d = max(sh, sf)
        worst = max(worst, d)
        flag = "ok" if d <= rtol else "DIFFERS"
        print(f"{name}: largest difference over each column's / array's magnitude: history {sh:.3g}, final arrays "
              f"{sf:.3g} ({flag}); element by element: history {dh:.3g}, final arrays {df:.3g}")
        ok = ok and d <= rtol
    print(f"worst relative difference {worst:.3g} (tolerance {rtol:g})")
    return ok


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--save")
    ap.add_argument("--compare")
    ap.add_argument("--rtol", type=float, default=1e-12)
    ap.add_argument("--quick", action="store_true", help="examples to 0.05 s, shared bed 500 steps")
    ap.add_argument("--only", choices=["dem", "coupled"], help="run only the DEM runs or only the coupled case")
    ap.add_argument("--threads", default="1",
                    help="threads of each process (default 1: the serial order; 'none' for a tree without --threads)")
    a = ap.parse_args()
    THREADS[:] = [] if a.threads == "none" else ["--threads", a.threads]
    res = collect(a.quick, a.only)
    if a.save:
        with open(a.save, "w") as fh:
            json.dump(res, fh)
    if a.compare:
        with open(a.compare) as fh:
            ref = json.load(fh)
        return 0 if compare(ref, res, a.rtol, a.only) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
