"""MPI runs (mpirun -np 1, 2, 3; 3 ranks oversubscribe the 2 cores): the same scene gives
the same trajectories and temperatures, restarts cross rank counts, and a particle that
crosses every rank boundary (a periodic one included) keeps its contacts and heat balance.

Tolerances: the ranks sum a particle's contact forces in another order than a serial run,
and in dense collisions that round-off grows. A serial run of tests/scenes/par_settle.toml
with another particle order (sort_interval 0 instead of 300) already differs by 7e-13 m in
position, 1.7e-9 m/s in velocity, 2.1e-6 rad/s in spin and 2.4e-12 K after its 1,000 steps;
the bounds below are about 100 times those, still 1e-7 of a radius.
"""
import csv
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dem import checkpoint
from dem.final import read as read_final

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(HERE, "scenes")

pytestmark = pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")


def mpirun(n, *args, cwd=None, check=True):
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
    cmd = ["mpirun", "-np", str(n), sys.executable, "-m", "dem", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def mpi_python(n, code, *args):
    """`python -c CODE ARGS` on n ranks (the environment of :func:`mpirun`)."""
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
    cmd = ["mpirun", "-np", str(n), sys.executable, "-c", code, *map(str, args)]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    if p.returncode != 0:
        raise AssertionError(f"mpirun -np {n} python -c ... failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def run(n, scene, out, *extra):
    mpirun(n, "run", os.path.join(SCENES, scene), "--out", str(out), "--quiet", *extra)
    return read_final(os.path.join(out, "final.npz"))


def history(out):
    with open(os.path.join(out, "history.csv")) as fh:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(fh)]


def assert_same(a, b, pos=1e-10, vel=1e-7, spin=5e-4, temp=1e-9):
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["position"] - b["position"]).max() <= pos
    assert np.abs(a["velocity"] - b["velocity"]).max() <= vel
    assert np.abs(a["angular_velocity"] - b["angular_velocity"]).max() <= spin
    if "temperature" in a.files:
        assert np.abs(a["temperature"] - b["temperature"]).max() <= temp


@pytest.fixture(scope="module")
def settle(tmp_path_factory):
    d = tmp_path_factory.mktemp("settle")
    return {n: (run(n, "par_settle.toml", d / f"np{n}"), d / f"np{n}") for n in (1, 2, 3)}


@pytest.fixture(scope="module")
def two_rank_5ms(tmp_path_factory):
    """par_settle.toml on 2 ranks to 5 ms: its checkpoint (a manifest and 2 pieces) is the one
    every test continuing or damaging a 2-rank checkpoint starts from (the same command each
    of them ran before; computed once). Tests that change the folder work on a copy."""
    out = tmp_path_factory.mktemp("two_rank_5ms") / "a"
    run(2, "par_settle.toml", out, "--end-time", "0.005")
    return out


@pytest.fixture(scope="module")
def periodic_serial(tmp_path_factory):
    """The serial run of par_periodic.toml (read by the two tests comparing a 3-rank run of it
    with the serial one; computed once)."""
    out = tmp_path_factory.mktemp("periodic") / "one"
    return run(1, "par_periodic.toml", out), out


@pytest.mark.parametrize("n", [2, 3])
def test_settling_conducting_bed_same_on_n_ranks(settle, n):
    """900 beads thrown onto a floor (dense collisions, rolling springs, conduction with a
    heated floor): 1,000 steps on n ranks match the serial run."""
    a, da = settle[1]
    b, db = settle[n]
    assert_same(a, b)
    ha, hb = history(da)[-1], history(db)[-1]
    assert hb["contacts"] > 500
    assert abs(ha["contacts"] - hb["contacts"]) <= 2  # a contact at the threshold may open or not
    assert hb["thermal_energy"] == pytest.approx(ha["thermal_energy"], rel=1e-12)
    assert hb["E_direct"] == pytest.approx(ha["E_direct"], rel=1e-6)
    assert hb["E_wall_floor"] == pytest.approx(ha["E_wall_floor"], rel=1e-9)


def test_conducting_packed_bed_euler_same_on_3_ranks(tmp_path):
    """Frozen 2,000-bead bed, direct + gap conduction with local porosity (read from ghosts
    across ranks) and a heated floor: 600 Euler heat steps on 3 ranks match serial to 1e-12 K."""
    a = run(1, "par_conduct.toml", tmp_path / "one")
    b = run(3, "par_conduct.toml", tmp_path / "three")
    assert np.abs(a["temperature"] - b["temperature"]).max() < 1e-11
    assert a["temperature"].max() > 380.0  # the floor heat reached the bed
    h = history(tmp_path / "three")
    gain = h[-1]["thermal_energy"] - h[0]["thermal_energy"]
    assert gain == pytest.approx(h[-1]["E_wall_heater"], rel=1e-9)


def test_exponential_update_conservative_on_3_ranks(tmp_path):
    """The exponential heat update across ranks: heat balance exact, temperatures within the
    scheme's own time-step error (serial exponential vs serial Euler: 0.028 K here)."""
    src = open(os.path.join(SCENES, "par_conduct.toml")).read()
    src = src.replace('integrator = "euler"', 'integrator = "exponential"')
    src = src.replace("../../examples/data", os.path.join(HERE, "..", "examples", "data"))
    scene = tmp_path / "expo.toml"
    scene.write_text(src)
    outs = {}
    for n in (1, 3):
        mpirun(n, "run", str(scene), "--out", str(tmp_path / f"np{n}"), "--quiet")
        outs[n] = read_final(tmp_path / f"np{n}" / "final.npz")
    rise = outs[1]["temperature"].max() - 300.0
    assert np.abs(outs[1]["temperature"] - outs[3]["temperature"]).max() < 1e-3 * rise
    h = history(tmp_path / "np3")
    gain = h[-1]["thermal_energy"] - h[0]["thermal_energy"]
    assert gain == pytest.approx(h[-1]["E_wall_heater"], rel=1e-9)


def test_periodic_crossing_keeps_contacts_and_heat(periodic_serial, tmp_path):
    """18 two-bead columns slide 35 mm along a 30 mm periodic axis cut into 3 slabs: every
    bead crosses every rank boundary and the periodic one. All 18 bead-bead and 18 floor
    contacts hold at every output, the contact springs equal the serial ones, heat is
    conserved to round-off and temperatures match the serial run."""
    a, one = periodic_serial
    b = run(3, "par_periodic.toml", tmp_path / "three")
    assert_same(a, b, pos=1e-14, vel=1e-12, spin=1e-9, temp=1e-11)
    hist = history(tmp_path / "three")
    assert all(r["contacts"] == 36 for r in hist[1:])
    e0 = hist[0]["thermal_energy"]
    assert all(abs(r["thermal_energy"] - e0) < 1e-12 * e0 for r in hist)
    assert hist[-1]["E_direct"] > 1e-4  # the pairs did conduct
    assert np.all(b["velocity"][:, 0] > 3.4)  # 35 mm in 10 ms: a full period
    ca = np.load(one / "checkpoint.npz")
    cb, _ = checkpoint.load(tmp_path / "three" / "checkpoint.npz")   # the manifest and its 3 pieces

    def springs(c):
        pair = c["rec_b"] - c["rec_a"] == 1  # the bead-bead contacts (ids 2k+1, 2k+2)
        order = np.argsort(c["rec_a"][pair])
        return c["rec_a"][pair][order], c["rec_hist"][pair][order]
    ka, sa = springs(ca)
    kb, sb = springs(cb)
    assert ka.size == 18 and np.array_equal(ka, kb)
    assert np.abs(sa).max() > 1e-8  # the springs are loaded (3.7e-8 m)
    assert np.abs(sa - sb).max() <= 1e-12 * np.abs(sa).max() + 1e-18


@pytest.mark.parametrize("first,second", [(2, 1), (1, 2), (2, 3)])
def test_restart_across_rank_counts(settle, two_rank_5ms, tmp_path, first, second):
    """A checkpoint written on `first` ranks continues on `second` ranks and ends where the
    uninterrupted serial run ends. (The 2-rank checkpoint at 5 ms is the shared two_rank_5ms,
    the same command this test ran; the restart only reads it.)"""
    ref, _ = settle[1]
    if first == 2:
        a = two_rank_5ms
    else:
        a = tmp_path / "a"
        run(first, "par_settle.toml", a, "--end-time", "0.005")
    b = run(second, "par_settle.toml", tmp_path / "b", "--restart", str(a / "checkpoint.npz"))
    assert_same(ref, b)


def test_slabs_thinner_than_the_halo_run(periodic_serial, tmp_path):
    """Slabs thinner than two halos (3 slabs along z through a 4 mm tall layer of beads) are
    legal on a non-periodic axis: each rank takes ghosts from every rank within one halo of
    its box, not only the next one (docs/reliability/mpi.md). The run matches the serial one."""
    src = open(os.path.join(SCENES, "par_periodic.toml")).read().replace('slab_axis = "x"', 'slab_axis = "z"')
    src = src.replace("../../examples/data", os.path.join(HERE, "..", "examples", "data"))
    scene = tmp_path / "thin.toml"
    scene.write_text(src)
    a, _ = periodic_serial
    p = mpirun(3, "run", str(scene), "--out", str(tmp_path / "thin"), "--quiet")
    assert "error" not in p.stderr
    b = read_final(tmp_path / "thin" / "final.npz")
    assert_same(a, b, pos=1e-14, vel=1e-12, spin=1e-9, temp=1e-11)


def test_each_rank_writes_its_own_checkpoint_piece(settle, two_rank_5ms, tmp_path):
    """An MPI checkpoint is a manifest (scalars, totals, the pieces and their sha256) and one piece
    per rank holding that rank's particles: no rank gathers the others' (issue 26). The pieces
    together hold every particle once; a second checkpoint removes the first one's pieces, and a
    newer piece left by a run killed before its manifest was written is not read.
    (The 2-rank run is the shared two_rank_5ms, copied since this test adds a piece and continues
    the run; it stops at 5 ms where this test's own run stopped at 4 ms: any time before the end
    gives a 2-piece checkpoint to continue.)"""
    out = tmp_path / "a"
    shutil.copytree(two_rank_5ms, out)
    man, _ = checkpoint.read(out / "checkpoint.npz")
    assert "state_position" not in man and man["pieces"].size == 2 and int(man["ranks"]) == 2
    folder = out / "checkpoint.pieces"
    step = int(man["step_count"])
    assert sorted(os.listdir(folder)) == [checkpoint.piece_name(step, 0), checkpoint.piece_name(step, 1)]
    whole, _ = checkpoint.load(out / "checkpoint.npz")
    final = read_final(out / "final.npz")
    assert int(man["piece_rows"].sum()) == final["id"].size and np.array_equal(whole["state_id"], final["id"])
    assert np.array_equal(whole["state_position"], final["position"])
    rows = [np.load(folder / str(n))["state_id"].size for n in man["pieces"]]
    assert rows == man["piece_rows"].tolist() and min(rows) > 0      # each rank wrote its own share
    # a piece of a later checkpoint that never got its manifest (a kill -9 between the two)
    stray = folder / checkpoint.piece_name(step + 100, 0)
    shutil.copy(folder / str(man["pieces"][0]), stray)
    b = run(3, "par_settle.toml", tmp_path / "b", "--restart", str(out / "checkpoint.npz"))
    ref = settle[1][0]
    assert_same(ref, b)
    mpirun(2, "run", os.path.join(SCENES, "par_settle.toml"), "--out", str(out), "--quiet", "--end-time", "0.006",
           "--restart", str(out / "checkpoint.npz"))
    man2, _ = checkpoint.read(out / "checkpoint.npz")
    assert sorted(os.listdir(folder)) == sorted(str(n) for n in man2["pieces"])   # earlier and stray pieces gone


def test_a_damaged_piece_is_refused_on_every_rank(two_rank_5ms, tmp_path):
    """A piece changed after it was written: every rank stops before anything runs, one line
    naming the piece (exit 2), on another rank count too. (The checkpoint is a copy of the shared
    2-rank one at 5 ms, two_rank_5ms, where this test ran its own to 2 ms: the time of the
    checkpoint does not enter the check of its pieces.)"""
    out = tmp_path / "a"
    shutil.copytree(two_rank_5ms, out)
    man, _ = checkpoint.read(out / "checkpoint.npz")
    piece = out / "checkpoint.pieces" / str(man["pieces"][1])
    data = dict(np.load(piece))
    data["state_velocity"] = data["state_velocity"] * 1.01
    with open(piece, "wb") as fh:
        np.savez(fh, **data)
    for n in (2, 3):
        p = mpirun(n, "run", os.path.join(SCENES, "par_settle.toml"), "--out", str(tmp_path / f"b{n}"), "--quiet",
                   "--restart", str(out / "checkpoint.npz"), check=False)
        assert p.returncode == 2, p.stderr
        assert "Traceback" not in p.stderr
        errs = [s for s in p.stderr.splitlines() if s.startswith("error:")]   # (mpirun adds its own banner)
        assert len(errs) == 1 and str(piece) in errs[0] and "does not match the sha256" in errs[0], p.stderr


# Runs a scene with every call on the communicator inside ParallelDomain._migrate and
# _send_ghosts noted (method, destination, tag, bytes of the buffer), and what the exchanges
# sent counted independently of the domain's counters: the records R.involving handed over
# (bytes from their declared dtypes) and the rows of every ghost message.
_SPY = r"""
import json, sys
import numpy as np
from dem.simulation import Simulation
from dem.parallel import domain as D
from dem import schema as S

sim = Simulation.from_file(sys.argv[1])
par, st = sim.par, sim.world.state
calls = []
seen = dict(migrates=0, ghost_exchanges=0, records=0, record_bytes=0, ghost_rows=0, foreign=0)
stage = [None]


class Spy:
    def __init__(self, comm):
        self._comm = comm

    def __getattr__(self, name):
        attr = getattr(self._comm, name)
        if not callable(attr):
            return attr

        def call(*args, **kw):
            if stage[0]:
                buf = args[0] if args and isinstance(args[0], np.ndarray) else None
                calls.append((stage[0], name, kw.get("dest"), kw.get("tag"), 0 if buf is None else int(buf.nbytes)))
            return attr(*args, **kw)
        return call


def staged(name, count):
    inner = getattr(D.ParallelDomain, name)

    def wrapped(self, *args):
        stage[0] = name
        first = len(calls)
        try:
            return inner(self, *args)
        finally:
            stage[0] = None
            seen[count] += 1
            if name == "_send_ghosts":
                seen["ghost_rows"] += sum(rows.size for _, rows, _ in self.sends)
                seen["foreign"] += sum(c[1] == "Isend" and c[2] not in self.neigh for c in calls[first:])
    setattr(D.ParallelDomain, name, wrapped)


def involving(rec, ids, _inner=D.R.involving):
    sub = _inner(rec, ids)
    ids_bytes = 2 * S.BY_NAME["id"].dtype.itemsize
    per = ids_bytes + sum(f.dtype.itemsize * int(np.prod(f.tail[1:])) for f in D.R.HISTORY if sub[f.name] is not None)
    seen["records"] += int(sub["a"].size)
    seen["record_bytes"] += int(sub["a"].size) * per
    return sub


base = dict(migrated=par.migrated, records=par.records_migrated, bytes_migrated=par.bytes_migrated,
            bytes_ghosts=par.bytes_ghosts)
par.comm = Spy(par.comm)
staged("_migrate", "migrates")
staged("_send_ghosts", "ghost_exchanges")
D.R.involving = involving
sim.run(end_time=float(sys.argv[2]))
declared = [f for f in S.of("particle") if f.migrate and S.enabled(f, st.features)]
assert all(getattr(st, f.name).dtype == f.dtype for f in declared)
row = {f.name: f.dtype.itemsize * int(np.prod(getattr(st, f.name).shape[1:])) for f in declared}
stats = par.stats(sim.world)
json.dump(dict(calls=calls, seen=seen, stats=stats, neigh=list(par.neigh),
               particle_bytes=sum(row.values()), ghost_bytes=sum(b for k, b in row.items() if S.BY_NAME[k].ghost),
               count_tag=D._TAG_GHOST_COUNT,
               migrated=par.migrated - base["migrated"], records=par.records_migrated - base["records"],
               bytes_migrated=par.bytes_migrated - base["bytes_migrated"],
               bytes_ghosts=par.bytes_ghosts - base["bytes_ghosts"],
               totals=dict(bytes_migrated=par.bytes_migrated, bytes_ghosts=par.bytes_ghosts,
                           records=par.records_migrated)),
          open(f"{sys.argv[3]}/rank{par.rank}.json", "w"))
"""


def test_rebuild_sends_typed_buffers_only(tmp_path):
    """At each exchange of a 3-rank run in which every bead crosses every rank boundary with
    its contact (tests/scenes/par_periodic.toml), migration and ghosts call only the typed
    (buffer) methods of the communicator, never a pickling one (alltoall, send, allgather:
    those gather the message of a failed rank only); ghosts go to neighbour ranks only, and
    migration buffers only where there is something to send. What a rank sent equals, to the
    byte, its migrated particles times the bytes of one particle's declared arrays (dem.schema)
    plus its records' ids and history, and its ghost rows times the declared ghost arrays;
    the counters say so, summed over the ranks in ``stats``."""
    import json
    mpi_python(3, _SPY, os.path.join(SCENES, "par_periodic.toml"), 0.01, tmp_path)
    ranks = [json.load(open(tmp_path / f"rank{r}.json")) for r in range(3)]
    for r, d in enumerate(ranks):
        pickled = [c for c in d["calls"] if c[1][0].islower()]
        assert not pickled, (r, pickled[:5])
        mig = [c for c in d["calls"] if c[0] == "_migrate"]
        gho = [c for c in d["calls"] if c[0] == "_send_ghosts"]
        assert sum(c[1] == "Alltoall" for c in mig) == d["seen"]["migrates"] > 10
        sends = [c for c in mig if c[1] == "Isend"]
        assert all(c[4] > 0 and c[2] != r for c in sends)
        assert sum(c[4] for c in sends) == d["bytes_migrated"]
        assert d["bytes_migrated"] == d["migrated"] * d["particle_bytes"] + d["seen"]["record_bytes"]
        assert d["records"] == d["seen"]["records"]
        assert d["seen"]["foreign"] == 0
        payload = sum(c[4] for c in gho if c[1] == "Isend" and c[3] != d["count_tag"])
        assert payload == d["bytes_ghosts"] == d["seen"]["ghost_rows"] * d["ghost_bytes"] > 0
    assert sum(d["migrated"] for d in ranks) > 36  # every bead crossed at least one rank boundary
    assert sum(d["records"] for d in ranks) > 0  # bead-bead contacts travelled with them
    st = ranks[0]["stats"]  # the run totals (any exchange before the spy included)
    assert st["bytes_migrated"] == sum(d["totals"]["bytes_migrated"] for d in ranks)
    assert st["bytes_ghosts"] == sum(d["totals"]["bytes_ghosts"] for d in ranks)
    assert st["records_migrated"] == sum(d["totals"]["records"] for d in ranks)


def test_dem_check_under_mpirun_reports_once(tmp_path):
    """`mpirun -np 2 dem check` prints its report once (rank 0 reports for every rank), the same
    lines as one process."""
    scene = os.path.join(SCENES, "par_settle.toml")
    serial = subprocess.run([sys.executable, "-m", "dem", "check", scene], capture_output=True, text=True,
                            timeout=300)
    assert serial.returncode == 0, serial.stderr
    p = mpirun(2, "check", scene)
    assert p.stdout.count("scene: ") == 1, p.stdout
    lines = lambda out: [s for s in out.splitlines() if s.startswith(("scene:", "particles:", "radius:", "time step:"))]
    assert lines(p.stdout) == lines(serial.stdout) and len(lines(serial.stdout)) == 4, (p.stdout, serial.stdout)
