"""``physgrad.fit``'s result as JSON (issue 53, item 5): ``json.dumps(result)`` writes the
summary, ``result.to_dict()`` the summary, the history and the run directory; the result is
read-only so that it never disagrees with its summary."""

import copy
import json
import math
import pickle

import numpy as np
import pytest

import physgrad
from physgrad.engine.types import Steps
from physgrad.harness.registry import METHODS
from physgrad.problems import HigToy


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    problem = HigToy(n_train=32, n_test=8)
    out = tmp_path_factory.mktemp("fit") / "run"
    return physgrad.fit(problem, METHODS["adam"](), budget=Steps(3), out=out, batch_size=16,
                        settings=physgrad.TrainSettings(eval_every=2))  # fmt: skip


def test_json_dumps_writes_the_summary(result: physgrad.FitResult):
    assert isinstance(result, dict) and result == result.summary  # pyright: ignore[reportUnnecessaryIsInstance]
    assert json.loads(json.dumps(result)) == json.loads(json.dumps(result.summary))
    assert json.loads(json.dumps(result))["steps"] == 3


def test_to_dict_holds_the_history_as_lists(result: physgrad.FitResult):
    data = json.loads(json.dumps(result.to_dict()))
    assert set(data) == {"summary", "history", "run_dir"}
    assert data["run_dir"] == str(result.run_dir) and data["summary"]["status"] == result["status"]
    assert data["history"]["step"] == [0, 2, 3]
    for name, column in result.history.items():  # every value, NaN where the column has none yet
        back = np.array([math.nan if v is None else v for v in data["history"][name]], np.float64)
        np.testing.assert_array_equal(back, column.astype(np.float64), err_msg=name)
    data["summary"]["steps"] = -1  # a copy: the result is untouched
    assert result["steps"] == 3


def test_read_only_and_copies(result: physgrad.FitResult):
    with pytest.raises(TypeError, match="read-only"):
        result["steps"] = 4
    with pytest.raises(TypeError, match="read-only"):
        result.update(steps=4)
    assert result["steps"] == result.summary["steps"] == 3
    # (the network holds jax.numpy.tanh, which pickle refuses: the copy pickled has none)
    bare = physgrad.FitResult(result.summary, result.history, run_dir=result.run_dir)
    for again in (pickle.loads(pickle.dumps(bare)), copy.copy(result), copy.deepcopy(bare)):
        assert again == result and again.run_dir == result.run_dir
        np.testing.assert_array_equal(again.history["step"], result.history["step"])
    mutable = dict(result)
    mutable["steps"] = 4
    assert result["steps"] == 3
