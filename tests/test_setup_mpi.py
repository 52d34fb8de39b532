"""Set-up per rank under MPI (issue 26, item 3): each rank reads only its slice of a packing
file (CSV by byte ranges aligned to line starts, NPZ members by row range), the particles go
to their owners through the migration, and a problem in any rank's slice is named with the
line or row the serial read names, on one line, exit 2, nothing written.

Runs through ``mpirun -np 2/3 python -m dem run`` on real processes. The final states are
compared by id with tests/test_parallel.py's bounds (contact forces summed in another order;
see its docstring).
"""
import math
import os
import re

import numpy as np
import pytest

from dem.final import read as read_final
from test_parallel import assert_same, mpirun

N = 648   # 9 x 9 x 8 beads


def packing(seed=3):
    """A loose lattice of beads (radius 1 mm +-5 %, 2.3 mm apart) with random velocities and
    ids in shuffled order (so that file order is not id order)."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(9), np.arange(9), np.arange(8), indexing="ij"), -1).reshape(-1, 3)
    x = 0.0015 + g * 0.0023 + rng.uniform(-1e-4, 1e-4, g.shape)
    r = rng.uniform(0.00095, 0.00105, len(g))
    v = rng.uniform(-0.2, 0.2, g.shape)
    ids = rng.permutation(len(g)) + 100
    return dict(x=x[:, 0], y=x[:, 1], z=x[:, 2], radius=r, vx=v[:, 0], vy=v[:, 1], vz=v[:, 2],
                id=ids.astype(float), temperature=300.0 + 50.0 * (x[:, 2] > 0.01))


def write_csv(path, cols, cells=None):
    """The packing as CSV: a comment and a blank line before the header; ``cells``: {(row,
    column): text} replaced. Returns the line number of each row."""
    names = list(cols)
    lines = ["# a packing written by the test", "", ",".join(names)]
    rows = []
    for k in range(len(cols["x"])):
        cell = [repr(float(cols[c][k])) if c != "id" else str(int(cols[c][k])) for c in names]
        for (rr, cc), t in (cells or {}).items():
            if rr == k:
                cell[names.index(cc)] = t
        lines.append(",".join(cell))
        rows.append(len(lines))
    path.write_text("\n".join(lines) + "\n")
    return rows


SCENE = """
[simulation]
time_step = 1e-5
end_time = 0.003
output_interval = 0.0015
gravity = [0.0, 0.0, -9.81]

[domain]
min = [0.0, 0.0, 0.0]
max = [0.024, 0.024, 0.03]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5
friction = 0.3
thermal_conductivity = 1.0
heat_capacity = 840.0

[[particles]]
material = "glass"
file = "{file}"

[thermal]
direct = "batchelor_obrien"

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "glass"
"""


def scene(tmp_path, file, name="s.toml"):
    p = tmp_path / name
    p.write_text(SCENE.replace("{file}", file))
    return p


def errors(p):
    """The error lines of a run (mpirun adds its own banner after a non-zero exit)."""
    assert "Traceback" not in p.stderr, p.stderr
    return [s for s in p.stderr.splitlines() if s.startswith("error:")]


def setup_rows(stdout):
    """(packing-file rows read, particle rows held) of the `parallel:` line (largest rank)."""
    m = re.search(r"at most (\d+) packing-file rows read and (\d+) particle rows held", stdout)
    assert m, stdout
    return int(m.group(1)), int(m.group(2))


@pytest.fixture(scope="module")
def bed(tmp_path_factory):
    d = tmp_path_factory.mktemp("bed")
    cols = packing()
    write_csv(d / "bed.csv", cols)
    np.savez(d / "bed.npz", position=np.stack([cols["x"], cols["y"], cols["z"]], 1),
             **{k: cols[k] for k in ("radius", "vx", "vy", "vz", "id", "temperature")})
    np.savez_compressed(d / "bedz.npz", **cols)
    mpirun(1, "run", str(scene(d, "bed.csv", "csv.toml")), "--out", str(d / "serial"), "--quiet")
    return d


@pytest.fixture(scope="module")
def npz_on_two_ranks(bed, tmp_path_factory):
    """The stored NPZ packing run on 2 ranks to the scene's end (3 ms): (CompletedProcess, output
    folder). Read by the (2, bed.npz) case of the slices test, and continued (from its checkpoint)
    by the restart test, which ran its own 2-rank run of this scene to 1 ms before: any 2-rank
    checkpoint of the scene shows that a restart on 3 ranks takes it and an edited radius is refused."""
    d = tmp_path_factory.mktemp("npz2")
    s = scene(d, os.path.join(str(bed), "bed.npz"))
    return mpirun(2, "run", str(s), "--out", str(d / "out")), d / "out"


@pytest.mark.parametrize("n,file", [(2, "bed.csv"), (3, "bed.csv"), (2, "bed.npz"), (3, "bedz.npz")])
def test_packing_file_read_by_slices_gives_the_serial_run(bed, request, tmp_path, n, file):
    """A CSV, a stored NPZ and a deflated NPZ on 2 and 3 ranks: the same final state by id as
    the serial run of the CSV, and no rank read or held more than its share of the rows (a CSV
    slice ends at a line start: a line's length in bytes more, 2 % slack; an NPZ slice is exact).
    (The stored NPZ on 2 ranks is the npz_on_two_ranks fixture, the same command, shared with the
    restart test.)"""
    if (n, file) == (2, "bed.npz"):
        p, out = request.getfixturevalue("npz_on_two_ranks")
    else:
        s = scene(tmp_path, os.path.join(str(bed), file))
        out = tmp_path / "out"
        p = mpirun(n, "run", str(s), "--out", str(out))
    a = read_final(bed / "serial" / "final.npz")
    b = read_final(out / "final.npz")
    assert_same(a, b)
    assert np.array_equal(np.sort(a["id"]), np.arange(100, 100 + N))
    read, held = setup_rows(p.stdout)
    share = math.ceil(N / n)
    slack = 0 if file.endswith(".npz") else math.ceil(0.02 * share)
    assert share <= read <= share + slack
    assert held <= share + slack


@pytest.mark.parametrize("file", ["bad.csv", "bad.npz"])
def test_bad_cell_in_the_second_slice_is_named_like_serial(tmp_path, file):
    """A non-number (CSV) or an infinite value (NPZ) in a row of the second rank's slice: the
    same one-line message as the serial run names the same line / row; exit 2; no output."""
    cols = packing()
    row = 3 * N // 4
    if file.endswith(".csv"):
        write_csv(tmp_path / file, cols, {(row, "vz"): "abc"})
    else:
        cols["vz"][row] = np.inf
        np.savez(tmp_path / file, **cols)
    s = scene(tmp_path, file)
    one = mpirun(1, "run", str(s), "--out", str(tmp_path / "o1"), check=False)
    two = mpirun(2, "run", str(s), "--out", str(tmp_path / "o2"), check=False)
    where = f"line {row + 4}" if file.endswith(".csv") else f"row {row}"
    assert one.returncode == two.returncode == 2
    err1, err2 = errors(one), errors(two)
    assert len(err2) == 1 and err2 == err1, (err1, err2)
    assert f"{file}: {where}, column vz: not a" in err2[0]
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


@pytest.mark.parametrize("kind", ["outside", "behind"])
def test_particle_outside_or_behind_a_wall_in_the_last_slice_is_named_like_serial(tmp_path, kind):
    """A particle of the third rank's slice outside the domain, or behind the unbounded floor:
    the serial message (id, line, position) on 3 ranks; exit 2; nothing written."""
    cols = packing()
    row = N - 10
    cols["z"][row] = 0.04 if kind == "outside" else -0.0005
    if kind == "behind":   # the floor at z = 0 with the domain starting below it
        src = SCENE.replace("min = [0.0, 0.0, 0.0]", "min = [0.0, 0.0, -0.002]")
    else:
        src = SCENE
    write_csv(tmp_path / "b.csv", cols)
    s = tmp_path / "s.toml"
    s.write_text(src.replace("{file}", "b.csv"))
    one = mpirun(1, "run", str(s), "--out", str(tmp_path / "o1"), check=False)
    three = mpirun(3, "run", str(s), "--out", str(tmp_path / "o3"), check=False)
    assert one.returncode == three.returncode == 2
    lines = errors(three)
    assert len(lines) == 1 and lines == errors(one)
    assert f"particle id {int(cols['id'][row])}" in lines[0]
    assert (f"(line {row + 4})" in lines[0]) if kind == "outside" else ("walls[0].normal" in lines[0])
    assert not (tmp_path / "o3").exists()


def test_mpi_restart_refuses_changed_particle_definitions(bed, npz_on_two_ranks, tmp_path):
    """A checkpoint of a 2-rank run continues on 3 ranks with the same packing file, and is
    refused (exit 2, one line) when a radius of the file changed: the per-rank set-up's
    digests (sums of per-particle hashes) are the same on any rank count and see the change.
    (The 2-rank run is the shared npz_on_two_ranks, at 3 ms: the restarts only read its
    checkpoint; the continued run goes 1 ms further.)"""
    s = scene(tmp_path, os.path.join(str(bed), "bed.npz"))
    ck = npz_on_two_ranks[1] / "checkpoint.npz"
    mpirun(3, "run", str(s), "--out", str(tmp_path / "b"), "--quiet", "--end-time", "0.004", "--restart", str(ck))
    cols = dict(np.load(bed / "bed.npz"))
    cols["radius"] = cols["radius"].copy()
    cols["radius"][N - 3] *= 1.01
    np.savez(tmp_path / "edited.npz", **cols)
    s2 = scene(tmp_path, str(tmp_path / "edited.npz"), "s2.toml")
    p = mpirun(3, "run", str(s2), "--out", str(tmp_path / "c"), "--quiet", "--end-time", "0.004", "--restart",
               str(ck), check=False)
    assert p.returncode == 2
    lines = errors(p)
    assert len(lines) == 1 and "the radii differ from the scene that wrote the checkpoint" in lines[0], lines


def test_repeated_id_across_slices_is_named_like_serial(tmp_path):
    """An id of the first rank's slice repeated in the third rank's: both lines named as the
    serial read names them."""
    cols = packing()
    cols["id"][N - 5] = cols["id"][7]
    write_csv(tmp_path / "dup.csv", cols)
    s = scene(tmp_path, "dup.csv")
    one = mpirun(1, "run", str(s), "--out", str(tmp_path / "o1"), check=False)
    three = mpirun(3, "run", str(s), "--out", str(tmp_path / "o3"), check=False)
    assert one.returncode == three.returncode == 2
    assert len(errors(three)) == 1 and errors(three) == errors(one)
    assert f"line {N - 5 + 4}, column id: id {int(cols['id'][7])} repeats (also on line {7 + 4})" in three.stderr


def test_overlap_across_the_slice_boundary_is_named_like_serial(tmp_path):
    """The last row of rank 0's NPZ slice overlaps the first row of rank 1's by 30 % of the
    smaller radius: found after the distribution (owned + ghosts) and named like the serial check."""
    cols = packing()
    k = N // 2 - 1
    assert k % 8 != 7   # k + 1 is its neighbour along z in the lattice: move it 0.3 r into k
    for c in "xyz":
        cols[c][k + 1] = cols[c][k]
    cols["z"][k + 1] += cols["radius"][k] + cols["radius"][k + 1] - 0.3 * min(cols["radius"][k], cols["radius"][k + 1])
    np.savez(tmp_path / "ov.npz", **cols)
    s = scene(tmp_path, "ov.npz")
    one = mpirun(1, "run", str(s), "--out", str(tmp_path / "o1"), check=False)
    two = mpirun(2, "run", str(s), "--out", str(tmp_path / "o2"), check=False)
    assert one.returncode == two.returncode == 2
    lines = errors(two)
    assert len(lines) == 1 and lines == errors(one)
    a, b = sorted((int(cols["id"][k]), int(cols["id"][k + 1])))
    ids = re.search(r"particles id (\d+) and id (\d+) overlap by 0.3 of the smaller radius", lines[0])
    assert ids and sorted(map(int, ids.groups())) == [a, b], lines
    assert not (tmp_path / "o2").exists()


def test_overlap_across_a_periodic_boundary_inside_one_box(tmp_path):
    """Two beads overlapping through the periodic x boundary, in a column cut along z (each
    rank's box spans x, so no ghost image carries the pair): named like the serial check."""
    pos = [[0.0005 + 0.0024 * (k % 4), 0.002, 0.0015 + 0.0025 * (k // 4)] for k in range(40)]
    pos[0][0] = 0.0002
    pos[3][0] = 0.0082   # 1.8 mm from pos[0] through the boundary: 20 % of the radius
    src = SCENE.replace('file = "{file}"', f"positions = {pos}\nradius = 0.001")
    src = src.replace("max = [0.024, 0.024, 0.03]", "max = [0.0098, 0.004, 0.03]\nperiodic = [true, false, false]")
    src = src.replace("[thermal]", "[thermal]\ninitial_temperature = 300.0")
    p = tmp_path / "per.toml"
    p.write_text(src)
    one = mpirun(1, "run", str(p), "--out", str(tmp_path / "o1"), check=False)
    two = mpirun(2, "run", str(p), "--out", str(tmp_path / "o2"), check=False)
    assert one.returncode == two.returncode == 2
    lines = errors(two)
    assert len(lines) == 1 and lines == errors(one)
    assert "particles id 1 and id 4 overlap by 0.2 of the smaller radius" in lines[0]


INSERT = """
[simulation]
time_step = 1e-5
end_time = 0.001
seed = 11

[domain]
min = [0.0, 0.0, 0.0]
max = [0.03, 0.03, 0.05]

[[materials]]
name = "glass"
density = 2500.0
youngs_modulus = 1e7
poisson_ratio = 0.25
restitution = 0.5

[parallel]
insertion_block = 400

[[particles]]
material = "glass"
count = 300
radius = 0.001
region = { type = "box", min = [0.0, 0.0, 0.0], max = [0.03, 0.03, 0.02] }

[[particles]]
material = "glass"
count = 1500
radius = { distribution = "uniform", min = 0.0006, max = 0.0009 }
region = { type = "box", min = [0.0, 0.0, 0.01], max = [0.03, 0.03, 0.04] }
"""


def test_insertion_by_blocks_same_particles_on_1_2_3_ranks(tmp_path):
    """A count group above parallel.insertion_block (1500 > 400: four blocks, dealt to the
    ranks) after a group of 300 inserted on one rank in an overlapping region: the initial
    particles (final.npz of a run to t = 0) are bitwise the same on 1, 2 and 3 ranks, none
    overlaps another, and every block's spheres stay inside their block (seams)."""
    p = tmp_path / "ins.toml"
    p.write_text(INSERT)
    got = {}
    for n in (1, 2, 3):
        out = tmp_path / f"np{n}"
        mpirun(n, "run", str(p), "--out", str(out), "--quiet", "--end-time", "0")
        z = read_final(out / "final.npz")
        got[n] = {k: z[k] for k in ("id", "position", "radius")}
    for n in (2, 3):
        for k in ("id", "position", "radius"):
            assert np.array_equal(got[1][k], got[n][k]), (n, k)
    x, r = got[1]["position"], got[1]["radius"]
    assert len(r) == 1800 and np.array_equal(got[1]["id"], np.arange(1, 1801))
    d = np.linalg.norm(x[:, None] - x[None], axis=2) - (r[:, None] + r[None])
    np.fill_diagonal(d, 1.0)
    assert d.min() >= 0.0
    # the big group: 4 blocks of 0.015 x 0.015 x 0.03 m (x and y halved); every sphere inside its block
    big = got[1]["id"] > 300
    edge = np.array([0.015, 0.015])
    xy = x[big, :2]
    cell = np.floor(xy / edge)
    inner = xy - cell * edge
    assert np.all(inner >= r[big, None] * (1 - 1e-12)) and np.all(edge - inner >= r[big, None] * (1 - 1e-12))
