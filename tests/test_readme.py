"""The README's own-simulator examples run as written and train."""

import re
from pathlib import Path

import equinox as eqx

import physgrad


def run_example(heading: str, factor: float):
    """Execute the first Python block after ``heading`` (a loop that trains ``net``, a whole
    Equinox module) and check the loss dropped ``factor``×."""
    text = (Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(rf"## {heading}.*?```python\n(.*?)```", text, re.S).group(1)
    setup, loop = code.split("\nfor _ in range")
    namespace = {}
    exec(compile(setup, "README.md", "exec"), namespace)
    batch = namespace["batch"]
    predict = namespace.get("predict") or (lambda p, s: namespace["simulate"](namespace["output"](p, s), s))
    objective = physgrad.Objective(predict, namespace["loss"])

    @eqx.filter_jit  # one program for the loss before and after (eagerly, op by op)
    def loss_of(net):  # the net as it is: its activation functions are not arrays
        arrays, static = eqx.partition(net, eqx.is_inexact_array)
        return objective.bind_static(static).batch_loss(arrays, batch)

    def batch_loss(net):
        return float(loss_of(net))

    initial = batch_loss(namespace["net"])
    exec(compile("for _ in range" + loop, "README.md", "exec"), namespace)
    final = batch_loss(namespace["net"])
    assert final < initial / factor, (initial, final)


def test_readme_example_trains():
    run_example("HIG on your own simulator", 100)


def test_readme_problem_object_trains_with_fit():
    # the HIG section's simulator as an AbstractProblem (issue 53: the README pointed to the
    # oscillators' module while its only problem example was a time-stepper)
    text = (Path(__file__).parents[1] / "README.md").read_text()
    section = re.search(r"## HIG on your own simulator(.*?)\n## ", text, re.S).group(1)
    code = re.findall(r"```python\n(.*?)```", section, re.S)[1]
    assert "class Mass(physgrad.AbstractProblem)" in code
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    history = namespace["result"].history
    assert namespace["result"]["status"] == "finished"
    assert history["test_loss"][-1] < history["test_loss"][0] / 10, history["test_loss"]


def test_readme_sip_example_trains():
    run_example("SIP on your own simulator", 10)


def test_readme_bptt_example_trains():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"## Back-propagation through time.*?```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    from physgrad.rollout import rollout

    system, batch = namespace["system"], namespace["batch"]
    initial = float(namespace["loss"])  # the rollout loss at the start (rollout.value_and_grad)
    final = float(rollout(system, namespace["params"], batch)[0])
    assert final < initial / 5, (initial, final)


def test_readme_time_stepper_example_trains(tmp_path, monkeypatch):
    from physgrad.harness.registry import PROBLEMS

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "cache"))
    text = (Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"## A neural time-stepper around your own solver.*?```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert "my_decay" not in PROBLEMS  # trained as an object: no registry write
    summary = namespace["result"].summary
    assert summary["status"] == "finished"
    # the exact step is 0.9048 u; the solver's 0.9 u leaves a correction to learn
    assert summary["final_test_metrics"]["rel_error"] < 1e-4, summary["final_test_metrics"]
