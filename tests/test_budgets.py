"""The budgets as objects: :class:`physgrad.Steps`, :class:`physgrad.Epochs` and
:class:`physgrad.Seconds` each answer whether they are met and how many steps are left; the
core asks them instead of comparing a kind's name."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

import physgrad
from physgrad import Budget, ConfigError, Epochs, Seconds, Steps


def test_the_keyword_spelling_builds_the_final_class_and_reads_back_from_its_record():
    assert Budget(steps=3) == Steps(3) and Budget(epochs=2) == Epochs(2) and Budget(seconds=1.5) == Seconds(1.5)
    for budget in (Steps(3), Epochs(2), Seconds(1.5)):
        assert isinstance(budget, Budget) and Budget.of(budget.to_dict()) == budget
        assert Budget(**budget.to_dict()) == budget
    assert str(Steps(3)) == "3 steps" and str(Seconds(1.5)) == "1.5 seconds" and Steps(3).kind == "steps"
    with pytest.raises(ConfigError, match="give exactly one budget"):
        Budget(steps=1, seconds=2)
    with pytest.raises(ConfigError, match=r"Budget\(steps=0\): steps must be a positive integer"):
        Steps(0)


def test_each_budget_says_whether_it_is_met_and_how_many_steps_are_left():
    epochs_at = lambda step: step / 10  # noqa: E731 — ten steps per epoch
    steps, epochs, seconds = Steps(25), Epochs(2), Seconds(3.0)
    assert not steps.met(24, 99.0, epochs_at) and steps.met(25, 0.0, epochs_at)
    assert steps.steps_left(20, 100, epochs_at) == 5 and steps.steps_left(20, 3, epochs_at) == 3
    assert not epochs.met(19, 99.0, epochs_at) and epochs.met(20, 0.0, epochs_at)
    assert epochs.steps_left(12, 100, epochs_at) == 8 and epochs.steps_left(0, 5, epochs_at) == 5
    assert not seconds.met(10**6, 2.9, epochs_at) and seconds.met(1, 3.0, epochs_at)
    assert seconds.steps_left(0, 7, epochs_at) == 7 and seconds.seconds_left(1.0) == 2.0
    assert steps.seconds_left(1.0) == math.inf == epochs.seconds_left(1.0)
    assert steps.first_met_at(25, epochs_at) and not steps.first_met_at(26, epochs_at)
    assert epochs.first_met_at(20, epochs_at) and not epochs.first_met_at(21, epochs_at)
    assert not seconds.first_met_at(1, epochs_at)
    assert epochs.meter_total(10) == 20 and seconds.meter(5, 1.0, 3.0) == (1.0, 2.0)


def test_the_core_does_not_compare_budget_kinds_by_name():
    root = Path(physgrad.__file__).parent
    found = []
    for path in root.rglob("*.py"):
        if "harness" in path.relative_to(root).parts:
            continue  # the command line keeps its strings at the edge
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\.kind\s*[!=]=", line) and "budget" in line:
                found.append(f"{path.relative_to(root)}:{number}")
    assert not found, found
