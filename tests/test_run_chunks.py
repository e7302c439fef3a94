"""The calibration times the run's own program and chunking (issue 50, item 4)."""

from __future__ import annotations

import dataclasses

import pytest

import physgrad
from physgrad.engine import strategies
from physgrad.harness.calibration import step_programs, time_programs
from physgrad.harness.config import make_config
from physgrad.harness.run_chunks import Replay, run_chunks
from physgrad.harness.train import train


def test_the_chunks_are_the_run_loops_between_evaluations():
    """4 batches an epoch, each with a new order, an evaluation every 6 steps: chunks end
    at each epoch's end and each evaluation, until both meet again (step 12)."""
    common = dict(steps_per_epoch=4, stage_steps=None, program_chunk=1024, eval_seconds=0.0, per_step=1e-4)
    assert run_chunks(epoch_end=True, eval_every=6, **common) == [(0, 0, 4), (1, 0, 2), (1, 2, 2), (2, 0, 4)]
    # the same order every epoch: only the evaluations cut the chunks
    assert run_chunks(epoch_end=False, eval_every=6, **common) == [(0, 0, 6), (1, 2, 6)]
    # a dear step: ChunkSize's 0.25 s of training per chunk
    assert [c for *_, c in run_chunks(**{**common, "per_step": 0.1}, epoch_end=False, eval_every=64)][:2] == [2, 2]
    # a step without a loop around it (a convolution on a CPU): one step a chunk
    assert {c for *_, c in run_chunks(**{**common, "program_chunk": 1}, epoch_end=True, eval_every=0)} == {1}


def test_a_replay_times_each_chunk_from_dispatch_to_read_back_with_the_state_carried():
    """A fake clock that the dispatch advances by 1 ms + 0.1 ms a step and the read-back by
    0.5 ms: a call takes whole chunks of the cycle until 10 ms, returns their steps and
    timed seconds (the draws of each epoch's order, between chunks, are not timed), and the
    parameters go from chunk to chunk."""
    now, seen, drawn = [0.0], [], []

    def clock():
        return now[0]

    def dispatch(params, opt_state, data, order, batch, count):
        seen.append((params, order, batch, count))
        now[0] += 1e-3 + 1e-4 * count
        return params + count, opt_state, count, False, {"loss": [0.0] * count}

    def read(result):
        now[0] += 5e-4
        return result

    def inputs(epoch):
        drawn.append(epoch)
        now[0] += 1.0  # not the chunk's time
        return "data", f"order{epoch}"

    chunks = [(0, 0, 4), (1, 0, 2), (1, 2, 2), (2, 0, 4)]
    replay = Replay(dispatch, read, inputs, (0, "opt"), chunks, clock=clock)
    steps, seconds = replay()
    assert [c for *_, c in seen] == [4, 2, 2, 4, 4, 2] and steps == 18
    assert abs(seconds - (6 * 1.5e-3 + 18 * 1e-4)) < 1e-12  # >= 10 ms after the 6th chunk
    assert [p for p, *_ in seen] == [0, 4, 6, 8, 0, 4]  # carried, and the cycle starts again
    assert [o for _, o, *_ in seen][:4] == ["order0", "order1", "order1", "order2"] and drawn[:3] == [0, 1, 2]
    # time_programs takes the replay's own seconds, not its clock around the call (the draws)
    assert time_programs({"m": [replay]}, repeats=1, clock=clock)["m"][0][0] < 2e-3


def test_a_replay_does_the_runs_work_between_chunks_untimed():
    """The cycle marks the chunks the run evaluates after (every 6 steps, and at the cycle's
    end); the replay hands every chunk's parameters, statistics and steps to ``between``,
    with whether the run evaluates there, and the 10 s ``between`` spends on the clock are
    not the chunks' time."""
    from physgrad.harness.run_chunks import chunk_cycle

    cycle = chunk_cycle(steps_per_epoch=4, epoch_end=True, stage_steps=None, program_chunk=1024, eval_every=6,
                        eval_seconds=0.0, per_step=1e-4)  # fmt: skip
    assert cycle == [((0, 0, 4), False), ((1, 0, 2), True), ((1, 2, 2), False), ((2, 0, 4), True)]
    now, seen = [0.0], []

    def dispatch(params, opt_state, data, order, batch, count):
        now[0] += 2**-9  # ~2 ms, exact in binary
        return params + count, opt_state, count, False, {"loss": [0.0] * count}

    def between(params, opt_state, stats, taken, evaluated):
        seen.append((params, len(stats["loss"]), taken, evaluated))
        now[0] += 10.0

    replay = Replay(dispatch, lambda r: r, lambda e: ("data", e), (0, "opt"), [c for c, _ in cycle],
                    clock=lambda: now[0], between=between, evaluated=[e for _, e in cycle])  # fmt: skip
    steps, seconds = replay()
    assert steps == 18 and seconds == 6 * 2**-9  # six chunks reach 10 ms; the 60 s between them are not counted
    assert seen == [(4, 4, 4, False), (6, 2, 2, True), (8, 2, 2, False), (12, 4, 4, True), (4, 4, 4, False),
                    (6, 2, 2, True)]  # fmt: skip


def test_the_calibration_replays_the_chunks_a_run_takes(tmp_path, monkeypatch):
    """hig_toy's Adam (4 batches an epoch, shuffled) with an evaluation every 6 steps: after
    its first epoch (the run's first chunk is one step) the run dispatches exactly the
    chunks the calibration's program replays, cycle after cycle."""
    config = make_config(
        "hig_toy", "adam", budget=physgrad.Budget(steps=40), settings={"eval_every": "6", "shuffle": "true"}
    )
    taken = []
    observe = strategies.ChunkSize.observe

    def counting(self, steps, seconds):
        taken.append(steps)
        observe(self, steps, seconds)

    monkeypatch.setattr(strategies.ChunkSize, "observe", counting)
    train(config, tmp_path / "run")
    (program,), _, _ = step_programs(config)
    cycle = [(4 * epoch + batch, count) for epoch, batch, count in program.chunks]
    assert cycle == [(0, 4), (4, 2), (6, 2), (8, 4)]
    starts = [sum(taken[:i]) for i in range(len(taken))]
    run = [(start, count) for start, count in zip(starts, taken) if start >= 4]
    assert run and all((start % 12, count) in cycle for start, count in run[:-1])  # the last: the budget's end


def test_the_calibration_does_what_the_run_does_between_its_chunks(tmp_path, monkeypatch):
    """What would make a calibrated step cost other than the run's: the calibration's program
    calls the very compiled chunk the run calls, with the same counts, and between chunks
    does the run's work in the run's order: the Recorder's evaluation (and its metrics
    row) and a checkpoint after the chunks the run evaluates after (hig_toy's Adam,
    shuffled, an evaluation every 6 steps: the run from step 12 on, one cycle of the
    replay). A chunk after a checkpoint costs more than one back to back (run_chunks.Bookkeeping)."""
    from physgrad.engine.recording import Checkpointer, Recorder
    from physgrad.engine.step import Program

    events, programs = [], set()
    call, record, save = Program.__call__, Recorder.__call__, Checkpointer.save

    def chunk(self, *args):
        programs.add(id(self.compiled))
        events.append(f"chunk {int(args[-1])}")
        return call(self, *args)

    monkeypatch.setattr(Program, "__call__", chunk)
    monkeypatch.setattr(
        Recorder, "__call__", lambda self, *a, **k: (events.append("evaluate"), record(self, *a, **k))[1]
    )
    monkeypatch.setattr(Checkpointer, "save", lambda self, state: (events.append("checkpoint"), save(self, state))[1])
    config = make_config(
        "hig_toy", "adam", budget=physgrad.Budget(steps=40), settings={"eval_every": "6", "shuffle": "true"}
    )
    train(config, tmp_path / "run")
    run, ran = events[:], set(programs)
    (program,), _, _ = step_programs(config)
    events.clear()
    programs.clear()
    while len([e for e in events if e.startswith("chunk")]) < len(program.chunks):
        program()
    replayed = events[: events.index("checkpoint", events.index("chunk 4", 1)) + 1]  # one cycle: 4, 2, 2, 4 steps
    assert replayed == ["chunk 4", "chunk 2", "evaluate", "checkpoint", "chunk 2", "chunk 4", "evaluate", "checkpoint"]
    assert any(run[i : i + len(replayed)] == replayed for i in range(len(run)))
    assert programs == ran and len(ran) == 1  # the run's compiled program itself


def test_compares_table_flags_a_method_whose_in_run_step_is_not_its_calibrated_one():
    """summary.csv's time_per_step (s) beside calibrated_ms_per_step: a ratio column, ``*``
    outside [1/1.2, 1.2], and a line under the table naming the method."""
    from physgrad.harness.seeds import TABLE_NOTE, aggregate, format_table, table_note

    def row(method, seed, wall, calibrated):
        return {"method": method, "seed": seed, "status": "finished", "final_test_loss": "0.1", "best_test_loss": "0.1",
                "steps": "100", "time_per_step": str(wall), "calibrated_ms_per_step": str(calibrated)}  # fmt: skip

    rows = [row("adam", s, 2e-3, 1.0) for s in range(3)] + [row("hig", s, 1.1e-3, 1.0) for s in range(3)]
    table = aggregate(rows, ["adam", "hig"])
    lines = format_table(table)
    assert lines[0][-2:] == ["calibrated ms/step", "wall / calibrated"]
    assert lines[1][-1] == "2.00 *" and lines[2][-1] == "1.10"
    note = table_note(table)
    assert note.startswith(TABLE_NOTE) and "adam 2.00x" in note and "hig" not in note.split("\n")[1]
    assert table_note(table[1:]) == TABLE_NOTE


# --- the in-run step on the calibration's clock -------------------------------------------------


class ProcessClock:
    """A fake CPU clock (``engine.cpu_clock.run_cpu_time``) for the engine's loop: each chunk (two readings, before
    the dispatch and after the read-back) costs exactly ``per_chunk`` CPU seconds."""

    def __init__(self, per_chunk):
        self.now, self.per_chunk, self.readings = 0.0, per_chunk, 0

    def __call__(self):
        self.readings += 1
        self.now += self.per_chunk if self.readings % 2 == 0 else 0.0
        return self.now


def _counted_run(monkeypatch, per_chunk):
    """The loop's clock replaced by :class:`ProcessClock` and its chunks counted (the steps of each)."""
    import importlib

    run_module = importlib.import_module("physgrad.engine.run")
    monkeypatch.setattr(run_module, "run_cpu_time", ProcessClock(per_chunk))
    taken = []
    observe = strategies.ChunkSize.observe
    monkeypatch.setattr(strategies.ChunkSize, "observe", lambda self, n, s: (taken.append(n), observe(self, n, s)))
    return taken


def test_a_run_records_its_cpu_seconds_per_step_beside_the_wall_clock(tmp_path, monkeypatch):
    """summary.json holds the wall-clock and the CPU seconds per step of the same chunks:
    with a CPU clock that charges each chunk 3 ms, cpu_seconds is 3 ms × the chunks
    the loop took (counted by hand) and cpu_time_per_step that over the steps; the wall
    clock's time_per_step is train_seconds over the steps, as before."""
    import json

    taken = _counted_run(monkeypatch, 3e-3)
    config = make_config("hig_toy", "adam", budget=physgrad.Budget(steps=24), settings={"eval_every": "8"})
    summary = train(config, tmp_path / "run")
    assert summary["steps"] == summary["cpu_steps"] == sum(taken) == 24
    assert summary["cpu_seconds"] == pytest.approx(3e-3 * len(taken), abs=1e-12)
    assert summary["cpu_time_per_step"] == pytest.approx(3e-3 * len(taken) / 24)
    assert summary["time_per_step"] == pytest.approx(summary["train_seconds"] / 24)
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["cpu_time_per_step"] == pytest.approx(
        summary["cpu_time_per_step"])  # fmt: skip


def test_a_resumed_run_counts_its_own_sessions_cpu_steps_and_old_checkpoints_load(tmp_path, monkeypatch):
    """The CPU counters are a process's own: the checkpoint does not keep them (a checkpoint
    written before they existed is the same file), and a run resumed from step 16 to 40
    divides its session's CPU seconds by its session's 24 steps, not by all 40."""
    import json

    run = tmp_path / "run"
    first = make_config("hig_toy", "adam", budget=physgrad.Budget(steps=16), settings={"eval_every": "8"})
    train(first, run)
    counters = json.loads((run / "checkpoint" / "counters.json").read_text())
    assert counters["step"] == 16 and not {"cpu_seconds", "cpu_steps"} & set(counters)
    taken = _counted_run(monkeypatch, 5e-3)
    summary = train(dataclasses.replace(first, budget=physgrad.Budget(steps=40)), run, resume=True)
    assert summary["steps"] == 40 and summary["cpu_steps"] == sum(taken) == 24
    assert summary["cpu_time_per_step"] == pytest.approx(5e-3 * len(taken) / 24)


def _rows(clock):
    """Three seeds of adam and hig: wall 2.0 and 1.1 ms/step, CPU 1.05 and 0.5 ms/step, both
    calibrated at 1 ms/step on ``clock`` (None: a summary.csv without the column)."""

    def row(method, seed, wall, cpu):
        return {"method": method, "seed": seed, "status": "finished", "final_test_loss": "0.1", "best_test_loss": "0.1",
                "steps": "100", "time_per_step": str(wall), "cpu_time_per_step": str(cpu),
                "calibrated_ms_per_step": "1.0", "calibration_clock": clock or ""}  # fmt: skip

    return [row("adam", s, 2e-3, 1.05e-3) for s in range(3)] + [row("hig", s, 1.1e-3, 0.5e-3) for s in range(3)]


def test_the_in_run_over_calibrated_ratio_is_on_the_calibrations_clock():
    """A calibration on the cpu clock compares the in-run CPU ms/step (adam 1.05, hig 0.50:
    hig flagged), one on the wall clock, or unrecorded, the in-run wall-clock (adam 2.00
    flagged); the note under the table names the clock where the rows record it."""
    from physgrad.harness.seeds import TABLE_NOTE, aggregate, calibration_ratio, format_table, table_note

    cpu = aggregate(_rows("cpu"), ["adam", "hig"])
    assert [calibration_ratio(t) for t in cpu] == pytest.approx([1.05, 0.5])
    lines = format_table(cpu)
    assert lines[0][-4:] == ["ms/step (wall)", "ms/step (cpu)", "calibrated ms/step", "cpu / calibrated"]
    assert lines[1][-4:] == ["2.00", "1.05", "1", "1.05"] and lines[2][-1] == "0.50 *"
    note = table_note(cpu).split("\n")
    assert note[0] == TABLE_NOTE and "both on the cpu clock" in note[1] and "cpu_clock" in note[1]
    assert note[2].startswith("* ") and "hig 0.50x" in note[2] and "adam" not in note[2]
    for clock in ("wall", None):
        wall = aggregate(_rows(clock), ["adam", "hig"])
        assert [calibration_ratio(t) for t in wall] == pytest.approx([2.0, 1.1])
        assert format_table(wall)[0][-2:] == ["calibrated ms/step", "wall / calibrated"]
        assert ("both on the wall clock" in table_note(wall)) == (clock == "wall") and "adam 2.00x" in table_note(wall)


def test_summary_csv_carries_the_cpu_step_and_the_calibrations_clock(tmp_path):
    """collect() puts each run's cpu_time_per_step and its study's calibration clock
    (calibration.json's "clock", "wall" where a record predates it) in summary.csv."""
    import json

    from physgrad.harness.study import collect, read_csv

    out = tmp_path / "study"
    config = make_config("hig_toy", "adam", budget=physgrad.Budget(steps=8), settings={"eval_every": "4"})
    summary = train(config, out / "runs" / "adam-0")
    assert 0 < summary["cpu_time_per_step"] < 1 and summary["cpu_steps"] == 8  # the real CPU clock
    cost = {"method": "adam", "batch_size": 4, "steps": None, "route": "", "seconds": 1e-3, "q25": 1e-3, "q75": 1e-3,
            "low": 1e-3, "high": 1e-3, "rounds": 3}  # fmt: skip
    record = {"version": 3, "problem": "hig_toy", "measured": "now", "methods": {"adam": {"stages": [cost]}}}
    for clock in ("cpu", None):
        (out / "calibration.json").write_text(json.dumps({**record, **({"clock": clock} if clock else {})}))
        collect(out)
        (row,) = read_csv(out / "summary.csv")
        assert float(row["cpu_time_per_step"]) == pytest.approx(summary["cpu_time_per_step"])
        assert row["calibration_clock"] == (clock or "wall") and float(row["calibrated_ms_per_step"]) == 1.0
