"""Threads inside a process (`dem run --threads N`, dem.step.interact_blocks), through the command
line on real processes: a run on 2 threads is deterministic (bit for bit the same twice, and
when interrupted and continued), agrees with 1 thread to round-off amplified by the collisions,
runs under mpirun with 2 threads per rank, and a thread count that cannot be used is refused
before anything is written."""
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "tests", "scenes", "threads_bed.toml")
MPI_ENV = dict(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMPI_MCA_mpi_yield_when_idle="1")
ARRAYS = ("position", "velocity", "angular_velocity", "temperature")


def _dem(*args, mpi=0, check=True):
    cmd = [sys.executable, "-m", "dem", "run", *args]
    if mpi:
        cmd = ["mpirun", "--oversubscribe", "--bind-to", "none", "-np", str(mpi), *cmd]
    p = subprocess.run(cmd, cwd=ROOT, env=dict(os.environ, **MPI_ENV), capture_output=True, text=True,
                       timeout=900)
    if check:
        assert p.returncode == 0, p.stderr
    return p


def _final(out):
    """The final state by particle id (an MPI run's pieces gathered by dem.final.read)."""
    from dem.final import read
    z = read(os.path.join(out, "final.npz"))
    order = np.argsort(np.asarray(z["id"]))
    return {k: np.asarray(z[k])[order] for k in ARRAYS}


def _wall_heat(out):
    """Heat through the floor since the start (J), from the last row of history.csv."""
    with open(os.path.join(out, "history.csv")) as fh:
        rows = [line.rstrip("\n").split(",") for line in fh]
    cols = rows[0]
    k = cols.index("E_wall_floor")
    return float(rows[-1][k])


def _rel(a, b):
    scale = max(float(np.abs(a).max()), float(np.abs(b).max()), 1e-300)
    return float(np.abs(a - b).max()) / scale


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("threads")
    out = {}
    for name, k in (("t2a", "2"), ("t2b", "2"), ("t1", "1")):
        d = str(tmp / name)
        p = _dem(SCENE, "--out", d, "--threads", k, "--quiet")
        out[name] = (d, p.stdout)
    return tmp, out


def test_two_threads_bit_for_bit_repeatable(runs):
    _, out = runs
    assert ", 2 threads" in out["t2a"][1]
    a, b = _final(out["t2a"][0]), _final(out["t2b"][0])
    for k in ARRAYS:
        assert np.array_equal(a[k], b[k]), k
    assert _wall_heat(out["t2a"][0]) == _wall_heat(out["t2b"][0])


def test_two_threads_agree_with_one_to_round_off(runs):
    """Another thread count sums each particle's forces in another order (round-off, 1e-16),
    which 300 steps of collisions amplify; measured about 1e-12 here. 1e-8 bounds it with
    margin while a wrong force on any particle (a lost or doubled pair across two blocks:
    about 1e-3 of the velocities after one step) fails it by orders of magnitude."""
    _, out = runs
    a, c = _final(out["t2a"][0]), _final(out["t1"][0])
    for k in ARRAYS:
        assert _rel(a[k], c[k]) < 1e-8, (k, _rel(a[k], c[k]))
    qa, qc = _wall_heat(out["t2a"][0]), _wall_heat(out["t1"][0])
    assert qa != 0.0 and abs(qa - qc) <= 1e-8 * abs(qc)


def test_interrupted_and_continued_on_two_threads_is_bit_for_bit(runs):
    tmp, out = runs
    d = str(tmp / "split")
    _dem(SCENE, "--out", d, "--threads", "2", "--end-time", "0.00075", "--quiet")
    _dem(SCENE, "--out", d, "--threads", "2", "--restart", os.path.join(d, "checkpoint.npz"), "--quiet")
    a, b = _final(out["t2a"][0]), _final(d)
    for k in ARRAYS:
        assert np.array_equal(a[k], b[k]), k


def test_two_ranks_of_two_threads_agree_with_serial(runs):
    """mpirun -np 2 with 2 threads per rank (not bound to one core each): the same kernels;
    another order of sums again."""
    tmp, out = runs
    d = str(tmp / "mpi")
    p = _dem(SCENE, "--out", d, "--threads", "2", "--quiet", mpi=2)
    assert "2 threads per rank" in p.stdout
    a, c = _final(d), _final(out["t1"][0])
    for k in ARRAYS:
        assert _rel(a[k], c[k]) < 1e-8, (k, _rel(a[k], c[k]))


@pytest.mark.parametrize("bad, says", [("0", "a whole number >= 1"), ("two", "a whole number >= 1"),
                                       ("4096", "at most")])
def test_bad_thread_count_refused_before_anything_is_written(tmp_path, bad, says):
    out = tmp_path / "out"
    p = _dem(SCENE, "--out", str(out), "--threads", bad, check=False)
    assert p.returncode == 2
    assert "--threads" in p.stderr and says in p.stderr
    assert "Traceback" not in p.stderr
    assert not out.exists()


def test_coupled_auto_leaves_the_gas_solver_its_core(tmp_path, solver):
    """The gas solver solves while the DEM steps (docs/architecture.md, "One coupled step"):
    `coupling run --threads auto` gives the DEM the cores this process may use less the gas
    solver's process (at least 1), and says so in its done line; an explicit count is taken."""
    from dem import threads
    case = os.path.join(ROOT, "openfoam_cases", "single_particle_heating")
    want = max(1, min(threads.limit(), threads.cores_available()) - 1)
    for arg, k in (("auto", want), ("1", 1)):
        p = subprocess.run([sys.executable, "-m", "coupling.run", "run", case, "--out", str(tmp_path / arg),
                            "--end-time", "0.003", "--threads", arg], cwd=ROOT, capture_output=True, text=True,
                           timeout=600)
        assert p.returncode == 0, p.stderr
        assert f"{k} DEM thread{'s' if k > 1 else ''})" in p.stdout, p.stdout[-2000:]


def _cross_counts(nb, nnb, bounds):
    """interact_blocks' offsets counted afresh in numpy: each block's pairs whose other particle
    lies in another block, summed in block order."""
    cnt = [0]
    for b in range(len(bounds) - 1):
        i0, i1 = bounds[b], bounds[b + 1]
        rows = nb[i0:i1]
        used = np.arange(nb.shape[1])[None, :] < nnb[i0:i1, None]
        cnt.append(cnt[-1] + int(((rows < i0) | (rows >= i1))[used].sum()))
    return np.array(cnt)


def test_pairs_across_blocks_kept_between_rebuilds_are_the_current_lists():
    """The offsets of the pairs across blocks are counted once per neighbour list (dem.schema XC).
    One compiled call of 300 steps, with rebuilds inside it, keeps them between steps and counts
    them again after each rebuild; 300 calls of one step count them every step (each call sets
    the list from Python). Both runs must be the same bit for bit, and the kept offsets must be
    those of the list the run ends with."""
    from dem import Simulation
    from dem import step as K
    sims = []
    for _ in range(2):
        sim = Simulation.from_file(SCENE)
        sim.set_threads(2)
        sim.step(1)
        sims.append(sim)
    kept, counted = sims
    t_build = float(kept.state.fp[K.FP.tbuild])
    kept.step(300)
    for _ in range(300):
        counted.step(1)
    st = kept.state
    assert float(st.fp[K.FP.tbuild]) > t_build  # the list was rebuilt inside the compiled call
    for name in ARRAYS:
        assert np.array_equal(getattr(st, name), getattr(counted.state, name)), name
    n, nown = st.n_owned + st.n_ghost, st.n_owned
    nblk = K.blocks(st.ip)
    assert nblk == 2
    bounds = [nown * b // nblk for b in range(nblk)] + [n]
    fresh = _cross_counts(st.nb, st.nnb, bounds)
    assert fresh[-1] > 0
    assert list(st.xcnt[K.XC.n:K.XC.nown + 1]) == [n, nown]
    assert np.array_equal(st.xcnt[K.XC.start:K.XC.start + nblk + 1], fresh)


def test_neighbour_rebuild_on_two_threads_is_the_serial_list():
    """The rows of the half list and their carried-over history are built on the run's threads
    (dem.neighbors.build_half_list, nthreads > 1), each row by one thread: the list, its counts
    and every history slot (tangential spring, rolling spring) are those of one thread, bit for
    bit, for a bed in motion whose springs are loaded."""
    from dem import Simulation
    from dem import step as K
    from dem.neighbors import Box, build_half_list
    sim = Simulation.from_file(SCENE)
    sim.set_threads(2)
    sim.step(3000)  # the beads have landed: thousands of loaded springs
    st = sim.state
    C = st.bundles()[1]
    assert np.count_nonzero(C.hist) > 1000 and np.count_nonzero(C.rhist) > 1000
    dom = Box(st.lo, st.hi, st.periodic)
    st.position[:] += 1e-5 * np.sin(np.arange(st.position.size)).reshape(st.position.shape)  # a new list
    builds = [build_half_list(st.position, st.radius, st.n, st.n_owned, dom, dom, sim.stepper.world.reach,
                              st.fp[K.FP.skin], C.nb.shape[1], C, k) for k in (1, 2)]
    (nb1, nnb1, h1, rh1, a1, m1), (nb2, nnb2, h2, rh2, a2, m2) = builds
    assert m1 == m2 and np.array_equal(nnb1, nnb2)
    used = np.arange(nb1.shape[1])[None, :] < nnb1[:, None]
    assert np.array_equal(nb1[used], nb2[used])
    assert not np.array_equal(nnb1, C.nnb)  # the list changed, and the history followed it
    for a, b in ((h1, h2), (rh1, rh2), (a1, a2)):
        assert np.array_equal(a, b)
    assert np.count_nonzero(h1) > 1000


def _reservoir_scene(integrator, radiation):
    """The threads bed with every per-particle heat link on: gas convection (Gunn), a heat source,
    the floor at a fixed temperature, and, with ``radiation``, radiation (Krause 2017) with a
    radiating floor; the pairs fused into the force loop (Euler) or swept exponentially."""
    import tomllib
    with open(SCENE, "rb") as fh:
        data = tomllib.load(fh)
    data["thermal"].update(convection="gunn", integrator=integrator, sources=[{"group": 0, "power": 1e-3}])
    data["gas"]["velocity"] = [0.0, 0.0, 0.3]
    if radiation:
        data["materials"][0]["emissivity"] = 0.8
        data["thermal"]["radiation"] = "krause_2017"
        data["walls"][0]["thermal"]["emissivity"] = 0.7
    return data


@pytest.mark.parametrize("integrator, radiation", [("euler", False), ("exponential", False), ("euler", True)])
def test_heat_links_on_two_threads_are_the_serial_step(integrator, radiation):
    """The heat step's per-particle links (walls, convection, radiation, sources, the exponential
    relaxation) run on blocks of rows (dem.thermal.heat._link_rows), and so do the radiation
    accumulators. From the same state, one heat step on 2 threads gives the temperatures and heat
    rates of 1 thread bit for bit (with radiation, whose accumulators are summed in another order,
    to 1e-14), and the run totals and the floor's records to round-off."""
    from dem import Simulation
    from dem import step as K
    from dem.thermal.heat import TOT
    sims = []
    for _ in range(2):
        sim = Simulation.from_dict(_reservoir_scene(integrator, radiation), base_dir=os.path.dirname(SCENE))
        sim.set_threads(1)
        sim.step(200)
        sims.append(sim)
    one, two = sims
    assert np.array_equal(one.state.temperature, two.state.temperature)
    two.set_threads(2)
    assert K.blocks(two.state.ip) == 2
    recs = []
    for sim in sims:
        P, C, W, TB, prm = sim.state.bundles()
        t0 = sim.state.temperature.copy()
        tot0, wtot0, wrad0 = prm.tot.copy(), W.wtot.copy(), W.wrad.copy()
        sim.stepper.phases(K.PH_HEAT)
        recs.append((sim.state.temperature.copy(), P.heat_rate.copy(), prm.tot - tot0, W.wtot - wtot0,
                     W.wrad - wrad0, sim.state.temperature - t0))
    (T1, Q1, tot1, wt1, wr1, dT1), (T2, Q2, tot2, wt2, wr2, dT2) = recs
    assert np.count_nonzero(dT1) > 4000  # every particle's temperature moved in this step
    if radiation:
        assert _rel(dT2, dT1) < 1e-12 and _rel(Q2, Q1) < 1e-12
        assert abs(wr1[0]) > 0.0  # the floor radiates
    else:
        assert np.array_equal(T1, T2) and np.array_equal(Q1, Q2)
    # the floor's conduction is in the heat step when it is not fused into the force loop (Euler)
    floor = integrator == "exponential" or radiation
    for k in (TOT.conv, TOT.src) + ((TOT.wall,) if floor else ()) + ((TOT.rad,) if radiation else ()):
        assert abs(tot1[k]) > 0.0, k
        assert abs(tot2[k] - tot1[k]) <= 1e-12 * abs(tot1[k]), k
    assert abs(wt1[0]) > 0.0 or not floor
    # steps in one compiled call: the radiation pass takes the pairs across blocks that the
    # interact phase kept for the list (dem.blocks.kept_cross_counts) instead of counting them
    one.step(20)
    two.step(20)
    assert _rel(two.state.temperature - T2, one.state.temperature - T1) < 1e-9
    assert np.allclose(wt2, wt1, rtol=1e-12, atol=0.0) and np.allclose(wr2, wr1, rtol=1e-12, atol=0.0)
