"""Compile once: a study's seeds share one compiled step and evaluation (physgrad.engine.programs)."""

import jax
import numpy as np
import pytest

from physgrad import Budget
from physgrad.engine import initial_network
from physgrad.engine.programs import ProgramCache, abstract_key, key, static_key
from physgrad.harness import study
from physgrad.problems import HigToy


class CompileCounter:
    """Counts the programs XLA builds while active (JAX's public monitoring events): backend
    compilations, and loads from the persistent compilation cache that the test session
    keeps (tests/conftest.py), which stand for a compilation done in an earlier run."""

    def __init__(self):
        self.count = 0
        self.active = False
        jax.monitoring.register_event_duration_secs_listener(self._duration_event)
        jax.monitoring.register_event_listener(self._event)

    def _duration_event(self, event, duration, **kwargs):
        if self.active and event == "/jax/core/compile/backend_compile_duration":
            self.count += 1

    def _event(self, event, **kwargs):
        if self.active and event == "/jax/compilation_cache/cache_hits":
            self.count += 1

    def __enter__(self):
        self.count, self.active = 0, True
        return self

    def __exit__(self, *exc):
        self.active = False


@pytest.fixture(scope="module")
def compiles():
    return CompileCounter()


def test_a_second_seed_of_a_study_compiles_nothing(tmp_path, compiles):
    # lam = 0.37 appears in no other test: the first seed must compile its programs
    settings = {"lam": 0.37, "eval_every": 2}
    with compiles:
        first = study.compare("hig_toy", ["adam", "hig"], [0], Budget(steps=4), tmp_path / "a", settings=settings,
                              echo=lambda s: None)  # fmt: skip
    assert compiles.count > 0 and all(r["status"] == "finished" for r in first)
    with compiles:
        second = study.compare("hig_toy", ["adam", "hig"], [1, 2], Budget(steps=4), tmp_path / "b", settings=settings,
                               echo=lambda s: None)  # fmt: skip
    assert compiles.count == 0
    assert all(r["status"] == "finished" for r in second)
    # the seeds differ in data and network, so their results do too
    losses = {r["seed"]: r["final_test_loss"] for r in first + second if r["method"] == "adam"}
    assert len(set(losses.values())) == 3
    # another setting is another program
    with compiles:
        study.compare("hig_toy", ["adam"], [0], Budget(steps=4), tmp_path / "c", settings={**settings, "lr": 0.002},
                      echo=lambda s: None)  # fmt: skip
    assert compiles.count > 0


def test_cached_step_gives_the_result_of_a_fresh_compile(tmp_path):
    from physgrad.engine import programs

    settings = {"lam": 0.41, "eval_every": 3}
    study.compare("hig_toy", ["hig"], [0], Budget(steps=3), tmp_path / "warm", settings=settings, echo=lambda s: None)
    cached = study.compare(
        "hig_toy", ["hig"], [1], Budget(steps=3), tmp_path / "a", settings=settings, echo=lambda s: None
    )
    programs.STEPS.clear()
    programs.EVALUATIONS.clear()
    fresh = study.compare(
        "hig_toy", ["hig"], [1], Budget(steps=3), tmp_path / "b", settings=settings, echo=lambda s: None
    )
    assert cached[0]["final_test_loss"] == fresh[0]["final_test_loss"]


def test_jitted_network_initialisation_equals_the_eager_one():
    problem = HigToy()
    key = jax.random.key(3)
    data = problem.make_data(jax.random.key(0))
    jitted, eager = initial_network(problem, key, data), problem.initial_network(key, data)
    for a, b in zip(jax.tree.leaves(jitted), jax.tree.leaves(eager)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_program_cache_keys_and_eviction():
    cache = ProgramCache(size=2)
    built = []
    build = lambda name: lambda: built.append(name) or name  # noqa: E731
    assert cache.get("a", build("a")) == ("a", False)
    assert cache.get("a", build("a2")) == ("a", True)
    cache.get("b", build("b"))
    cache.get("c", build("c"))  # evicts "a", the least recently used
    assert cache.get("a", build("a3")) == ("a3", False)
    assert cache.get(None, build("n")) == ("n", False) and cache.get(None, build("n2")) == ("n2", False)
    assert built == ["a", "b", "c", "a3", "n", "n2"] and (cache.hits, cache.misses) == (1, 6)
    # unhashable parts give no key; arrays are keyed by shape, dtype and sharding
    assert key("x", [1, 2]) is None and key("x", static={"w": jax.numpy.zeros(2)}) is None
    x = jax.numpy.zeros((2, 3))
    assert abstract_key({"a": x}) == abstract_key({"a": x + 1}) != abstract_key({"a": x[:1]})
    with pytest.raises(TypeError):
        static_key({"w": x})


@pytest.mark.slow  # two fresh command-line runs
def test_persistent_compilation_cache_from_the_command_line(tmp_path):
    """``--compilation-cache DIR`` turns on JAX's persistent cache in the CLI's own process
    (the library never touches JAX's configuration); compiled programs land in DIR. (JAX
    opens its cache once per process, so each case runs in its own interpreter.)"""
    import subprocess
    import sys
    import textwrap

    cli = textwrap.dedent(f"""
        import jax
        from physgrad.harness.cli import main
        assert jax.config.jax_compilation_cache_dir is None  # importing physgrad set nothing
        code = main(["train", "hig_toy", "--method", "hig", "--steps", "2", "--quiet",
                     "--out", {str(tmp_path / "run")!r}, "--compilation-cache", {str(tmp_path / "xla")!r}])
        assert code == 0, code
        assert jax.config.jax_compilation_cache_dir == {str(tmp_path / "xla")!r}
    """)
    library = textwrap.dedent(f"""
        import jax
        from physgrad.engine import programs
        programs.use_compilation_cache({str(tmp_path / "xla2")!r}, min_compile_seconds=0)
        jax.jit(lambda x: x * 3 + 1)(jax.numpy.ones(5)).block_until_ready()
    """)
    for code in (cli, library):
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
        assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "run" / "summary.json").exists()
    assert any((tmp_path / "xla2").iterdir())
