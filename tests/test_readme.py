"""The README's own-simulator example runs as written and trains."""

import re
from pathlib import Path

import equinox as eqx


def test_readme_example_trains():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"## HIG on your own simulator\s+```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    objective, params, batch = namespace["objective"], namespace["params"], namespace["batch"]
    initial = float(objective.batch_loss(eqx.partition(namespace["net"], eqx.is_inexact_array)[0], batch))
    final = float(objective.batch_loss(params, batch))
    assert final < initial / 100, (initial, final)


def test_readme_sip_example_trains():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"## SIP on your own simulator.*?```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    objective, params, batch = namespace["objective"], namespace["params"], namespace["batch"]
    initial = float(objective.batch_loss(eqx.partition(namespace["net"], eqx.is_inexact_array)[0], batch))
    final = float(objective.batch_loss(params, batch))
    assert final < initial / 10, (initial, final)
