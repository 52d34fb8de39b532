"""A run is a list of operations with triggers (dem.operations): a chunk never crosses a due
step, an operation runs exactly at the steps its trigger names, the order at one step is the
list's, and the chunking (or splitting a run in calls) changes no bit of the state."""
import random

import numpy as np
import pytest

from dem import Simulation, interrupt, operations as ops
from dem.simulation import SimulationError

DT = 1e-5


def scene(end_steps=120, sort=25, out=40, ck=0):
    """60 glass beads falling on a floor that moves sideways (each step's time enters the
    wall contact), Hertz-Mindlin with rolling friction."""
    return {
        "simulation": {"time_step": DT, "end_time": end_steps * DT, "gravity": [0, 0, -9.81], "seed": 3,
                       "output_interval": out * DT, "checkpoint_interval": ck * DT, "sort_interval": sort},
        "domain": {"min": [0, 0, 0], "max": [0.008, 0.008, 0.02]},
        "materials": [dict(name="g", density=2500.0, youngs_modulus=5e6, poisson_ratio=0.3,
                           restitution=0.5, friction=0.4, rolling_friction=0.05)],
        "contact": {"rolling": "epsd"},
        "particles": [{"material": "g", "count": 60, "radius": {"distribution": "uniform", "min": 4e-4, "max": 6e-4},
                       "region": {"type": "box", "min": [0, 0, 0], "max": [0.008, 0.008, 0.01]},
                       "velocity": [0.0, 0.0, -0.3]}],
        "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g",
                   "velocity": [0.05, 0.0, 0.0]}],
    }


class Recorder(ops.Operation):
    """A user operation: records (step, time, event) whenever its trigger fires."""

    def __init__(self, trigger, log, name="rec"):
        self.trigger, self.log, self.name = trigger, log, name

    def act(self, run, event):
        self.log.append((self.name, run.sim.step_count, run.sim.time, event))


def state_of(sim):
    st = sim.state
    order = np.argsort(st.id[:st.n_owned])
    return {k: getattr(st, k)[:st.n_owned][order].copy()
            for k in ("position", "velocity", "angular_velocity")}


# --------------------------------------------------------------------------- arithmetic

def test_every_next_due_is_the_next_multiple():
    e = ops.Every(7)
    assert [e.next_due(s) for s in (0, 1, 6, 7, 8, 13, 14)] == [7, 7, 7, 14, 14, 14, 21]
    assert ops.Every(0).next_due(5) is None and not ops.Every(0).fires(0, ops.PAUSE)
    assert ops.At(10).next_due(3) == 10 and ops.At(10).next_due(10) is None
    t = ops.Every(4) | ops.AtEnd(unless_every=4)
    assert t.next_due(5) == 8
    assert t.fires(8, ops.PAUSE) and not t.fires(9, ops.PAUSE)
    assert t.fires(9, ops.END) and not t.fires(8, ops.END)   # 8 was just written by Every(4)
    assert not t.fires(9, ops.STOP)


@pytest.mark.parametrize("seed", range(20))
def test_a_chunk_never_crosses_a_due_step(seed):
    """The loop's arithmetic with random intervals and chunk proposals: it pauses at every
    multiple of every interval (and only there or inside a chunk budget), and reaches the end."""
    rng = random.Random(seed)
    periods = [rng.choice([0, 1, 3, 7, 10, 64, 1000]) for _ in range(4)]
    plan = [Recorder(ops.Every(n), []) for n in periods]
    start, end = rng.randrange(0, 50), rng.randrange(60, 3000)
    s, pauses = start, []
    while s < end:
        nxt = ops.next_pause(plan, s, end)
        assert s < nxt <= end
        s += min(nxt - s, rng.choice([1, 2, 5, 50, 10 ** 6]))
        pauses.append(s)
    due = {m for n in periods if n for m in range(start + 1, end + 1) if m % n == 0} | {end}
    assert due <= set(pauses)
    assert pauses[-1] == end


# --------------------------------------------------------------------------- runs

def test_user_operation_runs_exactly_at_multiples_of_k(tmp_path):
    log = []
    sim = Simulation.from_dict(scene(end_steps=100))
    sim.run(out_dir=str(tmp_path / "o"), progress=False, operations=[Recorder(ops.Every(7), log)])
    steps = [s for _, s, _, e in log]
    assert steps == list(range(7, 101, 7))
    assert all(t == s * DT for _, s, t, _ in log)   # the time of step s is s * dt, exactly
    assert sim.step_count == 100
    hist = np.genfromtxt(tmp_path / "o" / "history.csv", delimiter=",", names=True)
    assert np.allclose(hist["time"], np.array([0, 40, 80, 100]) * DT, rtol=1e-12, atol=0)  # start, every 40, end


def test_operations_at_one_step_run_in_list_order():
    log = []
    a, b = Recorder(ops.Every(10), log, "a"), Recorder(ops.Every(5), log, "b")
    sim = Simulation.from_dict(scene(end_steps=20))
    sim.run(progress=False, operations=[a, b])
    assert [(n, s) for n, s, _, _ in log] == [("b", 5), ("a", 10), ("b", 10), ("b", 15), ("a", 20), ("b", 20)]


def test_any_chunking_and_split_calls_give_the_same_bits(monkeypatch):
    """One step per chunk, the adaptive chunks, extra pauses (Every(3)) and a run split in
    three calls end in bitwise the same state (sorting every 25 steps included)."""
    res = []
    for seconds, extra, cuts in (("1", [], [120]), ("0", [], [120]), ("1", [3], [120]), ("1", [], [17, 64, 120])):
        monkeypatch.setenv("THERMODEM_CHUNK_SECONDS", seconds)
        sim = Simulation.from_dict(scene())
        for c in cuts:
            sim.run(end_time=c * DT, progress=False, operations=[Recorder(ops.Every(k), []) for k in extra])
        assert sim.step_count == 120 and sim.time == 120 * DT
        res.append(state_of(sim))
    for r in res[1:]:
        for k in r:
            assert np.array_equal(r[k], res[0][k]), k
    assert np.ptp(res[0]["velocity"][:, 0]) > 0.0   # the moving floor dragged some beads


def test_stop_from_an_operation_writes_series_end_and_checkpoint(tmp_path):
    """A stop request is served at the next pause: the history closes with that step, the
    checkpoint holds it; StopRequested says where."""

    class StopAt(ops.Operation):
        trigger = ops.Every(30)

        def act(self, run, event):
            interrupt.request_stop()

    sim = Simulation.from_dict(scene(end_steps=120))
    try:
        with pytest.raises(interrupt.StopRequested) as stop:
            sim.run(out_dir=str(tmp_path / "o"), progress=False, operations=[StopAt()])
    finally:
        interrupt.clear()
    assert stop.value.step == 30 and stop.value.time == 30 * DT
    assert stop.value.checkpoint == str(tmp_path / "o" / "checkpoint.npz")
    z = np.load(tmp_path / "o" / "checkpoint.npz")
    assert int(z["step_count"]) == 30
    hist = np.genfromtxt(tmp_path / "o" / "history.csv", delimiter=",", names=True)
    assert np.allclose(hist["time"], np.array([0, 30]) * DT, rtol=1e-12, atol=0)
    assert not (tmp_path / "o" / "final.npz").exists()


def test_failure_in_an_operation_writes_failed_state_only(tmp_path):
    class Fail(ops.Operation):
        trigger = ops.At(50)

        def act(self, run, event):
            raise SimulationError("test failure at step 50")

    sim = Simulation.from_dict(scene(end_steps=120, ck=20))
    with pytest.raises(SimulationError, match="step 50"):
        sim.run(out_dir=str(tmp_path / "o"), progress=False, operations=[Fail()])
    f = np.load(tmp_path / "o" / "failed_state.npz")
    assert float(f["time"]) == 50 * DT
    assert int(np.load(tmp_path / "o" / "checkpoint.npz")["step_count"]) == 40   # the last periodic one
    assert not (tmp_path / "o" / "final.npz").exists()


class MeanHeight(ops.Operation):
    """The worked example of a writer (docs/architecture.md, "Adding a writer"): the bed's mean
    height every ``n`` steps and at the end, one CSV row each, gathered through the Simulation's
    public API and written by the root through root_write (a full disk under MPI stops every rank)."""

    def __init__(self, path, n):
        self.path, self.n = path, n
        self.trigger = ops.Every(n) | ops.AtEnd(unless_every=n)

    def start(self, run):
        if run.sim.is_root:
            run.sim.root_write(lambda: open(self.path, "w").write("time,mean_z\n"))

    def act(self, run, event):
        fa = run.sim.final_arrays()   # collective: every rank's particles ordered by id (None off the root)
        if fa is not None:
            row = f"{run.sim.time!r},{float(fa['position'][:, 2].mean())!r}\n"
            run.sim.root_write(lambda: open(self.path, "a").write(row))


def test_a_user_writer_gets_its_rows_from_the_public_api(tmp_path):
    path = tmp_path / "height.csv"
    sim = Simulation.from_dict(scene(end_steps=130))
    sim.run(progress=False, operations=[MeanHeight(str(path), 50)])
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    assert rows.shape == (3, 2)                                   # steps 50, 100 and the end (130)
    assert np.allclose(rows[:, 0] / DT, [50, 100, 130], rtol=0, atol=1e-6)
    assert rows[-1, 1] == float(state_of(sim)["position"][:, 2].mean())   # the end state (by id), exactly
    assert rows[0, 1] > rows[-1, 1]                               # the beads fall
