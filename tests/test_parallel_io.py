"""Issue 26, output and restart at cluster scale: an MPI run's final.npz is a manifest and one piece
per rank (no rank gathers the particles of the others), read by id as a serial run's final.npz, made
one file by `dem gather`, refused when a piece is damaged, never mixed after a kill -9; a restart on M
ranks reads an even share of the checkpoint's rows by slices (about N / M each, whatever the number
of pieces); a re-cut of the boxes sends typed buffers only.

Tolerances: those of tests/test_parallel.py (the ranks sum a particle's contact forces in another
order than a serial run; see its docstring).
"""
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from dem import checkpoint, final, pieces
from dem.final import read as read_final

HERE = os.path.dirname(os.path.abspath(__file__))
SCENES = os.path.join(HERE, "scenes")
SETTLE = os.path.join(SCENES, "par_settle.toml")
N = 900   # beads of par_settle.toml

pytestmark = pytest.mark.skipif(shutil.which("mpirun") is None, reason="needs Open MPI (mpirun)")

ENV = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
           OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")


def mpirun(n, *args, check=True, module=("-m", "dem")):
    cmd = ["mpirun", "-np", str(n), sys.executable, *module, *map(str, args)]
    p = subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=900)
    if check and p.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def dem(*args):
    return subprocess.run([sys.executable, "-m", "dem", *map(str, args)], capture_output=True, text=True,
                          env=ENV, timeout=300)


def assert_same(a, b, pos=1e-10, vel=1e-7, spin=5e-4, temp=1e-9):
    assert np.array_equal(a["id"], b["id"])
    assert np.abs(a["position"] - b["position"]).max() <= pos
    assert np.abs(a["velocity"] - b["velocity"]).max() <= vel
    assert np.abs(a["angular_velocity"] - b["angular_velocity"]).max() <= spin
    assert np.abs(a["temperature"] - b["temperature"]).max() <= temp


END = 0.008   # the runs of the `runs` fixture stop here


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """par_settle.toml to 8 ms on 1, 2 and 3 ranks. Their final outputs are the ones the final-output
    tests read, and their checkpoints (2 and 3 pieces) the ones the restart tests continue: each of
    those ran this same command to 8 ms itself (the final-output tests ran to 4 ms: any time gives a
    final output of one piece per rank, and the serial and the parallel runs still agree to the
    bounds of tests/test_parallel.py, which they keep to 10 ms there). Tests that change a folder
    work on a copy; `dem gather` adds its own file only, which no other test reads."""
    d = tmp_path_factory.mktemp("final")
    for n in (1, 2, 3):
        mpirun(n, "run", SETTLE, "--out", d / f"np{n}", "--quiet", "--end-time", END)
    return d


@pytest.mark.parametrize("n", [2, 3])
def test_final_output_is_a_piece_per_rank_read_by_id(runs, n):
    """final.npz of an n-rank run is a manifest naming n pieces (each rank's own rows, ordered by
    id, ids in the recorded range); read by id it equals the serial run's final.npz."""
    serial = np.load(runs / "np1" / "final.npz")
    out = runs / f"np{n}"
    man = final.read_manifest(out / "final.npz")
    assert "position" not in man and man["pieces"].size == n and int(man["ranks"]) == n
    assert sorted(os.listdir(out / "final.pieces")) == sorted(str(p) for p in man["pieces"])
    assert int(man["piece_rows"].sum()) == N and man["piece_rows"].min() > 0   # each rank wrote its share
    for name, rows, lo, hi in zip(man["pieces"], man["piece_rows"], man["piece_id_min"], man["piece_id_max"]):
        ids = np.load(out / "final.pieces" / str(name))["id"]
        assert ids.size == rows and np.all(np.diff(ids) > 0) and ids[0] == lo and ids[-1] == hi
    got = read_final(out / "final.npz")
    assert sorted(got.files) == sorted(serial.files)
    assert float(got["time"]) == float(serial["time"]) == pytest.approx(END)
    assert_same(serial, got)


def test_dem_gather_writes_one_file_and_keeps_a_users_file(runs, tmp_path):
    """`dem gather OUT` writes OUT/final_gathered.npz: the arrays of a serial final.npz, ordered by
    id, equal to the pieces read by id; it may replace its own file, never a user's."""
    out = runs / "np3"
    p = dem("gather", out)
    assert p.returncode == 0, p.stderr
    g = np.load(out / final.GATHERED)
    want = read_final(out / "final.npz")
    assert sorted(g.files) == sorted(np.load(runs / "np1" / "final.npz").files)
    for k in want.files:
        assert np.array_equal(g[k], want[k]), k
    assert np.all(np.diff(g["id"]) > 0) and g["id"].size == N
    assert dem("gather", out).returncode == 0          # its own file: replaced
    user = tmp_path / "user"
    shutil.copytree(runs / "np2", user)
    (user / final.GATHERED).write_bytes(b"a user's file")
    p = dem("gather", user)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert str(user / final.GATHERED) in p.stderr and "not written by dem gather" in p.stderr
    assert (user / final.GATHERED).read_bytes() == b"a user's file"


@pytest.mark.parametrize("how", ["value", "byte"])
def test_a_damaged_final_piece_is_refused_naming_it(runs, tmp_path, how):
    """A piece changed after it was written (a value rewritten with numpy, or one byte flipped in
    the file) is refused: `dem gather` exits 2 with one line naming the piece, no traceback."""
    out = tmp_path / "o"
    shutil.copytree(runs / "np2", out)
    man = final.read_manifest(out / "final.npz")
    piece = out / "final.pieces" / str(man["pieces"][1])
    if how == "value":
        data = dict(np.load(piece))
        data["temperature"] = data["temperature"].copy()
        data["temperature"][7] += 1e-9
        with open(piece, "wb") as fh:
            np.savez(fh, **data)
    else:
        with open(piece, "r+b") as fh:
            with pieces.NpzMembers(str(piece)) as z:
                _, _, off = z.members["velocity"]
            fh.seek(off + 8 * 100)
            b = fh.read(1)
            fh.seek(off + 8 * 100)
            fh.write(bytes([b[0] ^ 0x10]))
    p = dem("gather", out)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    errs = [s for s in p.stderr.splitlines() if s.startswith("error:")]
    assert len(errs) == 1 and str(piece) in errs[0] and "corrupted" in errs[0], p.stderr
    assert not (out / final.GATHERED).exists()
    with pytest.raises(final.FinalError, match=re.escape(str(piece))):
        read_final(out / "final.npz")


# A `dem run` whose rank 0 is killed (SIGKILL) after every piece of the final output is on disk and
# before its manifest is written.
_KILL_BEFORE_MANIFEST = r"""
import os, signal, sys
from dem import final
from dem.cli import main
inner = final.manifest
def manifest(*args, **kw):
    os.kill(os.getpid(), signal.SIGKILL)
final.manifest = manifest
sys.exit(main(sys.argv[1:]))
"""


def test_kill_9_between_pieces_and_manifest_leaves_the_previous_final_output(runs, tmp_path):
    """A run killed between its final pieces and its manifest leaves the previous final output whole
    (its manifest and the pieces it names, read as before); the next run removes the orphans.
    (The previous output is a copy of the fixture's 2-rank run at 8 ms, where this test ran its own
    to 1 ms; the continued runs go 1 ms further, as before.)"""
    out = tmp_path / "o"
    shutil.copytree(runs / "np2", out)
    before = read_final(out / "final.npz")
    names = set(os.listdir(out / "final.pieces"))
    ck = out / "checkpoint.npz"
    p = mpirun(2, "run", SETTLE, "--out", out, "--quiet", "--end-time", END + 0.001, "--restart", ck,
               check=False, module=("-c", _KILL_BEFORE_MANIFEST))
    assert p.returncode != 0
    left = set(os.listdir(out / "final.pieces"))
    assert names < left and len(left - names) == 2        # the new pieces are there, unnamed
    after = read_final(out / "final.npz")                  # the previous output, whole
    assert float(after["time"]) == pytest.approx(END)
    for k in before.files:
        assert np.array_equal(before[k], after[k]), k
    mpirun(2, "run", SETTLE, "--out", out, "--quiet", "--end-time", END + 0.001, "--restart", ck)
    man = final.read_manifest(out / "final.npz")
    assert sorted(os.listdir(out / "final.pieces")) == sorted(str(n) for n in man["pieces"])
    assert float(read_final(out / "final.npz")["time"]) == pytest.approx(END + 0.001)


# ------------------------------------------------------------------------------------ restarts
def restart_rows(stdout):
    """(rows taken per rank, rows read per rank) of the `restart:` line."""
    m = re.search(r"rows taken per rank \[([\d, ]+)\], rows read per rank \[([\d, ]+)\]", stdout)
    assert m, stdout
    return [int(v) for v in m.group(1).split(",")], [int(v) for v in m.group(2).split(",")]


@pytest.fixture(scope="module")
def two_rank_checkpoint(runs, tmp_path_factory):
    """par_settle.toml serially to 10 ms (d / "serial"), and on 2 ranks to 8 ms (d / "a", its
    checkpoint: 2 pieces; the `runs` fixture's 2-rank run, the same command, reached through a
    link; the tests only read it)."""
    d = tmp_path_factory.mktemp("restart")
    mpirun(1, "run", SETTLE, "--out", d / "serial", "--quiet")
    os.symlink(runs / "np2", d / "a")
    return d


@pytest.mark.parametrize("m", [3, 8])
def test_restart_reads_an_even_share_of_the_rows(two_rank_checkpoint, tmp_path, m):
    """A 2-piece checkpoint continued on 3 and on 8 ranks (oversubscribed): every rank takes at most
    ceil(N / m) rows and reads from the files no more than those and the blocks around them
    (dem.pieces); the run ends where the uninterrupted serial run ends."""
    d = two_rank_checkpoint
    man, _ = checkpoint.read(d / "a" / "checkpoint.npz")
    assert man["pieces"].size == 2 and int(man["piece_version"]) == pieces.PIECE_VERSION
    p = mpirun(m, "run", SETTLE, "--out", tmp_path / "b", "--quiet", "--restart", d / "a" / "checkpoint.npz")
    taken, read = restart_rows(p.stdout)
    share = -(-N // m)
    assert len(taken) == m and sum(taken) == N and max(taken) <= share and min(taken) >= N // m
    B = max(pieces.block_rows(int(r)) for r in man["piece_rows"])
    for t, r in zip(taken, read):
        assert t <= r <= t + 2 * 2 * (B - 1)   # at most two pieces touched, a partial block at each end
    assert_same(read_final(d / "serial" / "final.npz"), read_final(tmp_path / "b" / "final.npz"))


def test_restart_3_to_2_ranks(runs, two_rank_checkpoint, tmp_path):
    """A 3-piece checkpoint continued on 2 ranks: each takes half of the rows, from the pieces that
    hold them, and the run ends where the serial one ends. (The 3-rank run to 8 ms is the `runs`
    fixture's, the same command this test ran; the restart only reads it.)"""
    d = two_rank_checkpoint
    p = mpirun(2, "run", SETTLE, "--out", tmp_path / "b", "--quiet", "--restart", runs / "np3" / "checkpoint.npz")
    taken, read = restart_rows(p.stdout)
    assert taken == [N // 2, N // 2]
    assert_same(read_final(d / "serial" / "final.npz"), read_final(tmp_path / "b" / "final.npz"))


def test_version_1_pieces_still_continue(two_rank_checkpoint, tmp_path):
    """A checkpoint of version-1 pieces (whole-piece sha256, as written before the pieces were read
    by slices) still continues, on another rank count, to the serial run's end."""
    d = two_rank_checkpoint
    src = d / "a" / "checkpoint.npz"
    arrays, record = checkpoint.load(src)   # every row and record, verified
    old = tmp_path / "old" / "checkpoint.npz"
    folder = checkpoint.pieces_folder(old)
    os.makedirs(folder)
    step = int(arrays["step_count"])
    rows = [arrays["state_id"].size // 2, arrays["state_id"].size - arrays["state_id"].size // 2]
    names, sums = [], []
    ids = arrays["state_id"]
    for r, (lo, hi) in enumerate([(0, rows[0]), (rows[0], ids.size)]):
        mine = ids[lo:hi]
        piece = {k: v[lo:hi] for k, v in arrays.items() if np.ndim(v) and v.shape[0] == ids.size}
        sel = np.isin(arrays["rec_a"], mine) | np.isin(arrays["rec_b"], mine)
        piece.update({k: v[sel] for k, v in arrays.items() if k.startswith("rec_")})
        piece.update(format=np.str_(checkpoint.PIECE_FORMAT), format_version=np.int64(1))
        digest = checkpoint.content_digest(piece)
        piece["checksum"] = np.str_(digest)
        names.append(checkpoint.piece_name(step, r))
        sums.append(digest)
        np.savez(os.path.join(folder, names[-1]), **piece)
    scal = {k: v for k, v in arrays.items() if k not in ("pieces",) and not (np.ndim(v) and v.shape[0] == ids.size)
            and not k.startswith("rec_")}
    man = dict(scal, pieces=np.array(names), piece_sha256=np.array(sums), piece_rows=np.array(rows, np.int64))
    np.savez(old, **checkpoint.with_meta(man, record, version=1))
    assert "piece_version" not in checkpoint.read(old)[0]
    mpirun(3, "run", SETTLE, "--out", tmp_path / "b", "--quiet", "--restart", old)
    assert_same(read_final(d / "serial" / "final.npz"), read_final(tmp_path / "b" / "final.npz"))


# ------------------------------------------------------------------------------------ re-cuts
# Runs a scene with every call on the communicator inside Decomposition.build noted (a re-cut:
# the boxes are cut again when the load is uneven), and checks that the typed sum of the cuts
# gives the bits of mpi4py's pickled allreduce on random histograms.
_SPY_RECUT = r"""
import json, sys
import numpy as np
from dem.simulation import Simulation
from dem.parallel import decomposition as Dc

sim = Simulation.from_file(sys.argv[1])
par = sim.par
calls, builds = [], [0]


class Spy:
    def __init__(self, comm):
        self._comm = comm

    def __getattr__(self, name):
        attr = getattr(self._comm, name)
        if not callable(attr):
            return attr

        def call(*args, **kw):
            if builds[0] < 0:
                calls.append(name)
            return attr(*args, **kw)
        return call


inner = Dc.Decomposition.build


def build(self, comm, *args, **kw):
    builds[0] = -builds[0] - 1
    try:
        return inner(self, comm, *args, **kw)
    finally:
        builds[0] = -builds[0]


Dc.Decomposition.build = build
par.comm = Spy(par.comm)
sim.run(end_time=float(sys.argv[2]))
comm = par.comm._comm
rng = np.random.default_rng(comm.Get_rank())
same = 0
for _ in range(50):
    h = rng.random(256) * 10.0 ** rng.integers(-6, 7, 256)
    same += bool(np.array_equal(Dc.global_sum(comm, h), comm.allreduce(h)))
json.dump(dict(calls=calls, builds=builds[0], rebalances=par.rebalances, same=same),
          open(f"{sys.argv[3]}/rank{comm.Get_rank()}.json", "w"))
"""


def test_a_recut_sends_typed_buffers_only(tmp_path):
    """The 300-bead bed settling on 3 ranks re-cuts its boxes (tests/scenes/rel_mpi_settle.toml):
    every call on the communicator inside those cuts is a typed (buffer) one, none pickles, and
    the typed sum of the histograms equals mpi4py's pickled allreduce to the bit (the cuts of a
    multi-rank run keep their bits)."""
    mpirun(3, os.path.join(SCENES, "rel_mpi_settle.toml"), 0.03, tmp_path, module=("-c", _SPY_RECUT))
    ranks = [json.load(open(tmp_path / f"rank{r}.json")) for r in range(3)]
    for d in ranks:
        assert d["rebalances"] >= 1 and d["builds"] >= 1
        assert d["calls"] and all(c[0].isupper() for c in d["calls"]), d["calls"][:10]
        assert "Allgather" in d["calls"]
        assert d["same"] == 50
