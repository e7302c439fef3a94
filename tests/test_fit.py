"""physgrad.fit's result, in-memory runs, callbacks and record, each against an independent
reference: a hand-written optax loop given fit's documented keys, an empty working
directory, the evaluation steps, the hyperparameters passed."""

from __future__ import annotations

import json
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad.engine.hyperparams import UNKNOWN, optimizer_record
from physgrad.methods import Gradient

LR, BATCH, N = 1e-2, 32, 96  # 3 steps per epoch: chunks of steps run on past an epoch's end


class Square(physgrad.AbstractProblem):
    """Recover x from y = x + 0.2·x² (per component) with a small MLP."""

    n: int = N
    name: ClassVar[str] = "square"
    description: ClassVar[str] = "a test problem"
    source: ClassVar[str] = "tests/test_fit.py"

    def make_data(self, key):
        x = jax.random.uniform(key, (2 * self.n, 2), jnp.float32, -1.0, 1.0)
        data = {"x": x, "y": x + 0.2 * x**2}
        return {"train": jax.tree.map(lambda a: a[: self.n], data), "test": jax.tree.map(lambda a: a[self.n :], data)}

    def make_network(self, key):
        return physgrad.MLP((2, 8, 2), jax.nn.tanh, key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        return x + 0.2 * x**2

    def loss(self, y, sample):
        return jnp.sum((y - sample["y"]) ** 2)


ADAM = physgrad.Method(Gradient(), optax.adam(LR))  # one object: its compiled steps are shared by the tests
SETTINGS = physgrad.TrainSettings(eval_every=10)


def hand_written(problem: Square, steps: int, eval_at: list[int], seed: int = 0) -> dict[str, list[float]]:
    """Adam in a plain loop with fit's documented keys and fixed batch order; the mean
    train and test losses at the steps ``eval_at``."""
    key = jax.random.key(seed)
    data = problem.make_data(jax.random.fold_in(key, 0))
    params, static = eqx.partition(problem.initial_network(jax.random.fold_in(key, 1), data), eqx.is_inexact_array)
    optimizer = optax.adam(LR)
    opt_state = optimizer.init(params)

    @jax.jit
    def mean_loss(params, batch):
        net = eqx.combine(params, static)
        return jnp.mean(jax.vmap(lambda s: problem.loss(problem.simulate(problem.network_output(net, s), s), s))(batch))

    grad_of = jax.jit(jax.grad(mean_loss))

    per_epoch = N // BATCH
    losses: dict[str, list[float]] = {"train_loss": [], "test_loss": []}
    for step in range(steps + 1):
        if step in eval_at:
            losses["train_loss"].append(float(mean_loss(params, data["train"])))
            losses["test_loss"].append(float(mean_loss(params, data["test"])))
        if step == steps:
            break
        index = step % per_epoch
        batch = jax.tree.map(lambda a: a[index * BATCH : (index + 1) * BATCH], data["train"])
        grad = grad_of(params, batch)
        updates, opt_state = optimizer.update(grad, opt_state, params)
        params = optax.apply_updates(params, updates)
    return losses


def test_the_history_is_a_hand_written_loop_with_the_documented_keys(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=25), batch_size=BATCH, settings=SETTINGS, seed=3)
    history = result.history
    assert list(history)[:2] == ["step", "time"] and history["step"].tolist() == [0, 10, 20, 25]
    assert all(v.shape == (4,) for v in history.values())
    expected = hand_written(Square(), 25, [0, 10, 20, 25], seed=3)
    for name, values in expected.items():
        np.testing.assert_allclose(history[name], values, rtol=2e-5, err_msg=name)
    assert np.all(np.diff(history["time"]) >= 0) and np.isnan(history["train_time_per_step"][0])
    # the result reads as the summary, as fit's dict did
    assert result["status"] == "finished" and result["steps"] == 25 and dict(result) == result.summary
    assert result["final_test_loss"] == history["test_loss"][-1]
    assert isinstance(result.network, physgrad.MLP) and result.state.step == 25 and result.run_dir is None
    # out=None wrote nothing: the working directory stays empty
    assert list(tmp_path.iterdir()) == []


def test_a_run_directory_gives_the_same_history_and_metrics_csv_reads_back_as_it(tmp_path):
    memory = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=12), batch_size=BATCH, settings=SETTINGS)
    disk = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=12), batch_size=BATCH, settings=SETTINGS,
                        out=tmp_path / "run")  # fmt: skip
    read = physgrad.engine.history_from_metrics(tmp_path / "run" / "metrics.csv")
    assert set(memory.history) == set(disk.history) == set(read)
    for name in ("step", "train_loss", "test_loss"):
        np.testing.assert_array_equal(memory.history[name], disk.history[name])
        np.testing.assert_array_equal(read[name], disk.history[name])
    # a finished run resumed returns its summary and its history read back, trains nothing
    again = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=12), batch_size=BATCH, settings=SETTINGS,
                         out=tmp_path / "run", resume=True)  # fmt: skip
    assert again.summary == disk.summary and again.network is None
    np.testing.assert_array_equal(again.history["test_loss"], disk.history["test_loss"])


def test_callbacks_are_called_at_the_evaluations_and_checkpoints(tmp_path):
    calls, checkpoints = [], []

    class Checkpoints(physgrad.Callback):
        def on_checkpoint(self, step, path):
            assert (path / "manifest.json").exists()
            checkpoints.append(step)

    result = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=25), batch_size=BATCH, settings=SETTINGS,
                          out=tmp_path / "run", callbacks=[lambda step, metrics: calls.append((step, metrics)),
                                                           Checkpoints()])  # fmt: skip
    history = result.history
    assert [step for step, _ in calls] == history["step"].tolist() == [0, 10, 20, 25]
    for i, (_, metrics) in enumerate(calls):
        assert metrics["time"] == history["time"][i]
        assert metrics["test_loss"] == history["test_loss"][i] and metrics["train_loss"] == history["train_loss"][i]
    assert {10, 20, 25} <= set(checkpoints) and checkpoints == sorted(checkpoints)  # at each evaluation, the end
    in_memory = []
    physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=3), batch_size=BATCH,
                 callbacks=[Checkpoints(), lambda step, metrics: in_memory.append(step)])  # fmt: skip
    assert in_memory == [0, 3]  # default schedule: every epoch (3 steps); no checkpoints in memory


@pytest.mark.unchecked("wrong callbacks on purpose: fit's own one-line error")
def test_wrong_callbacks_and_a_resume_without_a_directory_are_one_line_errors():
    def run(**kwargs):
        physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=1), batch_size=BATCH, **kwargs)

    with pytest.raises(physgrad.ConfigError, match=r"callbacks\[1\] must be a physgrad.Callback") as bad:
        run(callbacks=[print, 3])
    with pytest.raises(physgrad.ConfigError, match=r"wrap it in a list: callbacks=\[") as single:
        run(callbacks=print)
    with pytest.raises(physgrad.ConfigError, match="resume=True needs the run directory") as resume:
        run(resume=True)
    assert all("\n" not in str(e.value) for e in (bad, single, resume))


def test_the_record_names_the_method_and_its_optimizer_hyperparameters(tmp_path):
    injected = optax.chain(
        optax.clip_by_global_norm(1.0), optax.inject_hyperparams(optax.adam)(learning_rate=3e-3, b1=0.85)
    )
    method = physgrad.Method(Gradient(), injected)
    result = physgrad.fit(Square(), method, budget=physgrad.Budget(steps=4), batch_size=BATCH, out=tmp_path / "a",
                          name="mine")  # fmt: skip
    record = json.loads((tmp_path / "a" / "config.json").read_text())
    assert record["method"] == "mine" and result["method"] == "mine" and result["stage_steps"] == {"mine": 4}
    (hyperparameters,) = record["optimizers"][0]
    assert hyperparameters["learning_rate"] == 3e-3 and hyperparameters["b1"] == 0.85
    assert hyperparameters["b2"] == 0.999 and hyperparameters["eps"] == 1e-8
    # a schedule is recorded as one, with its first value; an optimizer without injected
    # hyperparameters says so
    scheduled = optax.inject_hyperparams(optax.sgd)(learning_rate=optax.linear_schedule(0.5, 0.1, 10))
    (recorded,) = optimizer_record(physgrad.Method(Gradient(), scheduled))
    assert (
        isinstance(recorded, dict) and recorded["learning_rate"] == "schedule (0.5 at step 0; its form is not recorded)"
    )
    physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=1), batch_size=BATCH, out=tmp_path / "b")
    record = json.loads((tmp_path / "b" / "config.json").read_text())
    assert record["optimizers"] == [UNKNOWN] and record["method"] == "Method"
    # another learning rate is another run; another name is the same run
    other = physgrad.Method(Gradient(), optax.chain(optax.clip_by_global_norm(1.0),
                                                    optax.inject_hyperparams(optax.adam)(learning_rate=1e-3, b1=0.85)))  # fmt: skip
    with pytest.raises(physgrad.ConfigError, match="different configuration"):
        physgrad.fit(Square(), other, budget=physgrad.Budget(steps=6), batch_size=BATCH, out=tmp_path / "a",
                     name="mine", resume=True)  # fmt: skip
    more = physgrad.fit(Square(), method, budget=physgrad.Budget(steps=6), batch_size=BATCH, out=tmp_path / "a",
                        name="renamed", resume=True)  # fmt: skip
    assert more["steps"] == 6 and more["method"] == "renamed"


def test_a_run_recorded_before_the_hyperparameters_resumes(tmp_path):
    run_dir = tmp_path / "old"
    physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=2), batch_size=BATCH, out=run_dir)
    record = json.loads((run_dir / "config.json").read_text())
    del record["optimizers"], record["method"]  # as an older physgrad wrote it
    (run_dir / "config.json").write_text(json.dumps(record))
    more = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=4), batch_size=BATCH, out=run_dir, resume=True)
    assert more["steps"] == 4 and more.history["step"].tolist() == [0, 2, 3, 4]


def _scalars(logdir) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the event files in ``logdir``, read back record by record (TFRecord
    framing: length, its CRC, the Event protobuf, its CRC)."""
    import struct

    from tensorboardX.proto import event_pb2

    scalars: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(logdir.glob("events.out.tfevents.*")):
        data, offset = path.read_bytes(), 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset : offset + 8])
            record = data[offset + 12 : offset + 12 + length]
            event = event_pb2.Event.FromString(record)  # pyright: ignore[reportAttributeAccessIssue]
            offset += 12 + length + 4
            for value in event.summary.value:
                scalars.setdefault(value.tag, []).append((event.step, value.simple_value))
    return scalars


def test_the_tensorboard_callback_writes_every_evaluation(tmp_path):
    pytest.importorskip("tensorboardX")
    from physgrad.engine.tensorboard import TensorBoard

    with TensorBoard(tmp_path / "tb", prefix="adam/") as board:
        result = physgrad.fit(Square(), ADAM, budget=physgrad.Budget(steps=25), batch_size=BATCH, settings=SETTINGS,
                              callbacks=[board])  # fmt: skip
    scalars = _scalars(tmp_path / "tb")
    steps = result.history["step"].tolist()
    for name in ("train_loss", "test_loss", "time"):
        written = scalars["adam/" + name]
        assert [step for step, _ in written] == steps, name
        np.testing.assert_allclose([v for _, v in written], result.history[name], rtol=1e-6, err_msg=name)
    # time_per_step is NaN at step 0 and not written there
    assert [step for step, _ in scalars["adam/train_time_per_step"]] == steps[1:]


def test_a_divergent_step_inside_a_chunk_ends_the_run_before_it():
    """SGD at a step size that diverges: fit stops at the first step whose batch loss is not
    finite (inside a chunk of steps), with the parameters before it, as a step-by-step
    loop finds them."""
    lr, steps = 40.0, 60
    result = physgrad.fit(Square(), physgrad.Method(Gradient(), optax.sgd(lr)), budget=physgrad.Budget(steps=steps),
                          batch_size=BATCH, settings=physgrad.TrainSettings(eval_every=steps))  # fmt: skip
    problem = Square()
    key = jax.random.key(0)
    data = problem.make_data(jax.random.fold_in(key, 0))
    params, static = eqx.partition(problem.initial_network(jax.random.fold_in(key, 1), data), eqx.is_inexact_array)

    @jax.jit
    def step(params, index):
        batch = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, index * BATCH, BATCH), data["train"])

        def mean_loss(p):
            net = eqx.combine(p, static)
            per_sample = jax.vmap(lambda s: problem.loss(problem.simulate(problem.network_output(net, s), s), s))
            return jnp.mean(per_sample(batch))

        loss, grad = jax.value_and_grad(mean_loss)(params)
        return jax.tree.map(lambda p, g: p - lr * g, params, grad), loss

    finite, first_bad = None, None
    for i in range(steps):
        new, loss = step(params, i % (N // BATCH))
        if not np.isfinite(float(loss)):
            first_bad = i
            break
        params, finite = new, float(loss)
    assert first_bad is not None and first_bad > 0 and finite is not None, "the reference does not diverge: raise lr"
    assert result["status"] == "diverged" and result["diverged_step"] == first_bad == result["steps"]
    np.testing.assert_allclose(result["last_finite_loss"], finite, rtol=1e-4)
    kept = eqx.filter(result.network, eqx.is_inexact_array)
    for a, b in zip(jax.tree.leaves(kept), jax.tree.leaves(params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.unchecked("a Setup without an objective: the loop never asks for it")
def test_chunks_end_at_every_event_the_loop_must_see():
    from physgrad.engine.strategies import ChunkSize, StopRule
    from physgrad.engine.types import Setup, Stage

    chunks = ChunkSize(target_seconds=0.25)
    assert chunks.size(1000) == 1  # the first chunk: its speed is unknown
    chunks.observe(10, 0.01)  # 1 ms per step
    assert chunks.size(1000) == 250 and chunks.size(7) == 7
    assert chunks.size(1000, seconds_left=0.1) == 50  # half the time to a timed event
    assert chunks.size(1000, seconds_left=0.0) == 1
    chunks.reset()
    assert chunks.size(1000) == 1
    # an epochs budget over two stages of different batch sizes: the first step that meets it
    stages = [Stage(ADAM, 32, 3, 0, 4), Stage(ADAM, 16, 6, 4, None)]
    setup = Setup(Square(), {}, None, None, None, stages)  # pyright: ignore[reportArgumentType]
    rule = StopRule(physgrad.Budget(epochs=2), setup)
    for step in range(0, 8):
        first = next(k for k in range(1, 100) if rule.met(step + k, 0.0))
        assert rule.steps_left(step, 1000) == first and rule.steps_left(step, 2) == min(first, 2), step


class ConvSquare(Square):
    """Square with a convolutional network: the two components as a one-channel signal of
    length two, through two 1-D convolutions (so the step holds a convolution)."""

    def make_network(self, key):
        k1, k2 = jax.random.split(key)
        return (
            eqx.nn.Conv1d(1, 4, 2, padding="SAME", dtype=jnp.float32, key=k1),
            eqx.nn.Conv1d(4, 1, 2, padding="SAME", dtype=jnp.float32, key=k2),
        )

    def network_output(self, network, sample):
        first, second = network
        return second(jnp.tanh(first(sample["y"][None])))[0]


def test_loop_chunk_is_one_for_a_convolution_on_a_cpu_and_the_whole_chunk_otherwise():
    from physgrad.engine.step import CHUNK, loop_chunk

    x, w = jnp.ones((1, 2, 8)), jnp.ones((3, 2, 3))
    conv = jax.jit(lambda x, w: jax.lax.conv_general_dilated(x, w, (1,), "SAME")).lower(x, w)
    dense = jax.jit(lambda a, b: jnp.tanh(a @ b)).lower(jnp.ones((4, 4)), jnp.ones((4, 4)))
    assert loop_chunk(conv, "cpu") == 1
    assert loop_chunk(conv, "gpu") == loop_chunk(dense, "cpu") == loop_chunk(dense, "gpu") == CHUNK


def test_a_convolutional_step_runs_one_per_dispatch_and_trains_as_a_hand_written_loop():
    """On a CPU a convolution inside a loop body runs many times slower (engine.step.loop_chunk),
    so the run compiles the step alone, with no loop (not even a one-iteration one), and
    dispatches it once per step: the history is still the hand-written loop's."""
    from physgrad.engine.step import Program, Steps
    from physgrad.engine.strategies import Placement
    from physgrad.engine.types import TrainState

    steps, eval_at = 25, [0, 10, 20, 25]
    result = physgrad.fit(ConvSquare(), ADAM, budget=physgrad.Budget(steps=steps), batch_size=BATCH,
                          settings=SETTINGS, seed=3)  # fmt: skip
    expected = hand_written(ConvSquare(), steps, eval_at, seed=3)
    assert result.history["step"].tolist() == eval_at
    for name, values in expected.items():
        np.testing.assert_allclose(result.history[name], values, rtol=2e-5, err_msg=name)

    setup = physgrad.engine.setup.build_setup(ConvSquare(), [physgrad.Phase(ADAM, None, BATCH)], 0)
    engine_steps = Steps(setup, Placement(), physgrad.TrainSettings(), 0)
    state = TrainState(setup.params, ADAM.init(setup.params))
    program, _ = engine_steps.compile(state, setup)
    assert isinstance(program, Program) and program.chunk == (1 if jax.default_backend() == "cpu" else 1024)
    if program.chunk == 1:
        assert "while" not in program.compiled.as_text()
        # asked for more steps, the program takes one (the run never asks: its chunk is 1)
        out = program(state.params, state.opt_state, engine_steps.data, engine_steps.order(0, 0), np.int32(0),
                      np.int32(5))  # fmt: skip
        assert int(out[2]) == 1 and not bool(out[3]) and out[4]["loss"].shape == (1,)


def test_a_divergent_convolutional_step_is_not_applied():
    """The one-step program keeps the loop's rule: a step whose loss is not finite leaves the
    parameters as they were and ends the run as diverged at that step."""
    lr = 1e4
    result = physgrad.fit(ConvSquare(), physgrad.Method(Gradient(), optax.sgd(lr)), budget=physgrad.Budget(steps=40),
                          batch_size=BATCH, settings=physgrad.TrainSettings(eval_every=40))  # fmt: skip
    assert result["status"] == "diverged" and result["diverged_step"] == result["steps"] > 0
    assert np.isfinite(result["last_finite_loss"])
    assert all(
        bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(eqx.filter(result.network, eqx.is_inexact_array))
    )
