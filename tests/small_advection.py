"""The small advection_1d configuration that the time-stepper test modules share, and the
fixture that sends their generated datasets to a per-session directory (import
``data_cache`` into a test module to apply it there: it is autouse)."""

from __future__ import annotations

import pytest

from physgrad.harness.config import Budget, make_config

SMALL_ADV = {"n_train": 4, "n_test": 3, "horizon": 16, "iterations": 6}


@pytest.fixture(autouse=True)
def data_cache(tmp_path_factory, monkeypatch):
    """Generated datasets go to a per-session directory, not the user's cache."""
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path_factory.getbasetemp() / "physgrad-cache"))


def adv_config(method, steps=5, **settings):
    return make_config("advection_1d", method, budget=Budget(steps=steps), settings={**SMALL_ADV, **settings})
