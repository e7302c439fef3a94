"""physgrad.fit's progress display (issue 53 item 3): a Rich bar when standard output is a
terminal, nothing otherwise, none with progress=False, and a meter object used as it is."""

from __future__ import annotations

import io

import optax
import pytest
from rich.console import Console

import physgrad
import physgrad._fit as public_fit
from physgrad.engine.progress import AbstractProgressMeter, NoProgressMeter, RichProgressMeter
from physgrad.methods import Gradient
from physgrad.problems import HigToy


def short_fit(**kwargs):
    adam = physgrad.Method(Gradient(), optax.adam(1e-3))
    return physgrad.fit(HigToy(), adam, budget=physgrad.Steps(3), label="toy-adam", **kwargs)


def terminal(monkeypatch, *, is_terminal: bool) -> io.StringIO:
    """Standard output's console replaced by one writing to a buffer, a terminal or not."""
    buffer = io.StringIO()
    console = Console(file=buffer, force_terminal=is_terminal, width=120)
    monkeypatch.setattr(public_fit, "_console", lambda: console)
    return buffer


def test_no_bar_when_standard_output_is_no_terminal(capsys, monkeypatch):
    buffer = terminal(monkeypatch, is_terminal=False)
    short_fit()
    assert buffer.getvalue() == ""
    assert capsys.readouterr().out == ""  # pytest's captured stdout is no terminal either


def test_a_bar_in_a_terminal(monkeypatch):
    buffer = terminal(monkeypatch, is_terminal=True)
    result = short_fit()
    shown = buffer.getvalue()
    assert "toy-adam" in shown and "step" in shown and "loss" in shown  # the bar's label and fields
    assert result["steps"] == 3


def test_progress_false_is_silent_in_a_terminal(monkeypatch):
    buffer = terminal(monkeypatch, is_terminal=True)
    short_fit(progress=False)
    assert buffer.getvalue() == ""


def test_progress_true_asks_for_the_bar_where_no_terminal_is(monkeypatch):
    # a notebook's output is no terminal; Rich draws its bar there as a widget (not testable
    # here: a plain buffer gets nothing from a transient bar), so the choice is what is tested
    terminal(monkeypatch, is_terminal=False)
    assert isinstance(public_fit._meter(True), RichProgressMeter)
    assert isinstance(public_fit._meter(None), NoProgressMeter)


def test_a_meter_object_is_used_as_it_is(monkeypatch):
    buffer = terminal(monkeypatch, is_terminal=True)
    calls: list[str] = []

    class Recording(AbstractProgressMeter):
        def start(self, **kwargs):
            calls.append("start")

        def update(self, **kwargs):
            calls.append("update")

        def close(self):
            calls.append("close")

    short_fit(progress=Recording())
    assert calls[0] == "start" and calls[-1] == "close" and "update" in calls
    assert buffer.getvalue() == ""  # no bar of fit's own beside it


@pytest.mark.unchecked("a wrong progress on purpose: fit's own one-line error")
def test_a_wrong_progress_is_one_line():
    with pytest.raises(physgrad.ConfigError, match="progress must be None .* got 'yes'"):
        short_fit(progress="yes")
