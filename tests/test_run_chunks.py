"""The calibration times the run's own program and chunking (issue 50, item 4)."""

from __future__ import annotations

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
