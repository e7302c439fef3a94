"""physgrad.fit limits the BLAS/LAPACK pools for its own duration (threads=1 by default, as
the command line does; issue 53 item 3) and restores them; threads=None leaves them alone."""

from __future__ import annotations

import inspect

import optax
import pytest
from threadpoolctl import threadpool_info

import physgrad
from physgrad.engine import run
from physgrad.methods import Gradient
from physgrad.problems import HigToy


def blas_threads() -> set[int]:
    return {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"}


def test_the_public_fit_takes_the_engines_arguments_and_threads():
    public = inspect.signature(physgrad.fit).parameters
    engine = inspect.signature(run.fit).parameters
    assert list(public) == [*engine, "threads"]
    for name, p in engine.items():
        # progress: the public fit also takes True/False (a bar in a terminal by default; issue 53 item 3)
        annotation = p.annotation.replace(" | None", " | bool | None") if name == "progress" else p.annotation
        assert (public[name].kind, public[name].default, public[name].annotation) == (p.kind, p.default, annotation)
    assert public["threads"].default == 1 and public["threads"].kind is inspect.Parameter.KEYWORD_ONLY
    doc = physgrad.fit.__doc__ or ""
    assert "threads=None" in doc and (run.fit.__doc__ or "").strip() in doc  # help() shows both


def fit_seeing_pools(**kwargs) -> set[int]:
    seen: set[int] = set()
    adam = physgrad.Method(Gradient(), optax.adam(1e-3))
    physgrad.fit(HigToy(), adam, budget=physgrad.Budget(steps=2), settings=physgrad.TrainSettings(eval_every=1),
                 callbacks=[lambda step, m: seen.update(blas_threads())], **kwargs)  # fmt: skip
    return seen


def test_fit_limits_the_pools_while_it_runs_and_restores_them():
    with physgrad.threads(2):  # a caller's own setting, distinct from fit's default
        assert fit_seeing_pools() == {1}
        assert blas_threads() == {2}
        assert fit_seeing_pools(threads=None) == {2}  # left alone
        assert fit_seeing_pools(threads=2) == {2}
        assert blas_threads() == {2}
    with pytest.raises(ValueError, match="positive integer"):
        fit_seeing_pools(threads=0)
