"""The core install without the optional extras (kfac-jax: ``physgrad[kfac]``, exponax:
``physgrad[pde]``): physgrad imports and trains; a method or problem that needs a missing
extra says so in one line.

Nothing is uninstalled: a fresh interpreter gets a ``sitecustomize`` that makes importing
kfac_jax and exponax impossible (``sys.modules[name] = None``, as for a package that is
not there), so every physgrad import and the command line see a core-only environment.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from test_validation import module_entry

BLOCKED = ("kfac_jax", "exponax")

SCRIPT = """
import contextlib, io, json, sys, tempfile
import physgrad
from physgrad.harness.cli import main
from physgrad.harness.config import make_config
from physgrad.engine import Budget
from physgrad.extras import MissingExtra
from physgrad.harness.registry import METHODS

out = {"imported": sorted(n for n in ("kfac_jax", "exponax") if sys.modules.get(n) is not None)}
d = tempfile.mkdtemp()
out["runs"] = {}
for problem, method in (("hig_toy", "hig"), ("hig_toy", "adam"), ("sine", "sip")):
    with contextlib.redirect_stdout(io.StringIO()):
        out["runs"][f"{problem}/{method}"] = main(["train", problem, "--method", method, "--steps", "3", "--quiet",
                                                    "--set", "eval_every=3", "--out", f"{d}/{problem}-{method}"])
listing = io.StringIO()
with contextlib.redirect_stdout(listing):
    main(["list"])
out["marked"] = [line.split()[0] for line in listing.getvalue().splitlines() if "physgrad[" in line]
errors = {}
for name, call in (("kfac", lambda: METHODS["kfac"]()),
                   ("ks", lambda: make_config("ks", "one", budget=Budget(steps=1)))):
    try:
        call()
    except MissingExtra as e:
        errors[name] = [type(e).__mro__[1].__name__, isinstance(e, ImportError), str(e)]
out["errors"] = errors
print(json.dumps(out))
"""


def core_only_env(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text("import sys\n" + "".join(f"sys.modules[{n!r}] = None\n" for n in BLOCKED))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site), *filter(None, [env.get("PYTHONPATH")])])
    env["PHYSGRAD_CACHE"] = str(tmp_path / "cache")
    return env


# A fresh interpreter trains three runs core-only (15 s of CPU). The fast tier keeps the
# missing-extra message (the test below); .ci/smoke.sh trains from a core-only wheel as well.
@pytest.mark.slow
def test_core_install_trains_and_names_the_missing_extras(tmp_path):
    env = core_only_env(tmp_path)
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(SCRIPT)], capture_output=True, text=True,
                            env=env, cwd=tmp_path, timeout=600)  # fmt: skip
    assert result.returncode == 0, result.stderr[-4000:]
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert out["imported"] == []
    assert out["runs"] == {"hig_toy/hig": 0, "hig_toy/adam": 0, "sine/sip": 0}
    assert sorted(out["marked"]) == ["advection_1d", "kfac", "kfac_hig", "kolmogorov", "ks"]
    assert out["errors"]["kfac"] == ["ConfigError", True, "kfac needs the kfac extra: pip install 'physgrad[kfac]'"]
    assert out["errors"]["ks"] == [
        "ConfigError",
        True,
        "the ks problem needs the pde extra: pip install 'physgrad[pde]'",
    ]


@pytest.mark.costly("the fast tier's one check that the command line names a missing extra: a fresh interpreter")
def test_command_line_names_the_missing_extra_in_one_line(tmp_path):
    env = core_only_env(tmp_path)
    probes = [
        ["train", "hig_toy", "--method", "kfac", "--steps", "1"],
        ["train", "ks", "--method", "one", "--steps", "1"],
    ]
    lines = ["kfac needs the kfac extra: pip install 'physgrad[kfac]'",
             "the ks problem needs the pde extra: pip install 'physgrad[pde]'"]  # fmt: skip
    # both through ``python -m physgrad`` in one core-only interpreter (test_validation.module_entry)
    results = module_entry([[*args, "--out", str(tmp_path / "run")] for args in probes], env=env, cwd=tmp_path)
    for (code, out, err), line in zip(results, lines, strict=True):
        assert code == 2
        assert err.strip() == f"physgrad: error: {line}"
        assert "Traceback" not in out + err
