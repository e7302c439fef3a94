"""Your own problem and method on the command line (issue 53, item 2): ``physgrad train
module:Class`` by import path, and the ``physgrad.problems`` / ``physgrad.methods`` entry
points of an installed package (physgrad.harness.plugins).

The package is written into ``tmp_path`` with a ``*.dist-info`` beside it, which is what an
installer leaves in site-packages: ``importlib.metadata`` finds its ``entry_points.txt`` on
``sys.path`` as it finds an installed one's (the slow test below installs it with pip)."""

import base64
import hashlib
import json
import re
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

from physgrad.errors import ConfigError
from physgrad.harness.cli import main
from physgrad.harness.plugins import PluginWarning, Registry, is_import_path, method_factory, problem_class
from physgrad.harness.registry import METHODS, PROBLEMS

PACKAGE = "physgrad_demo_plugin"

# The throwaway package: a problem (a network's output doubled by the "simulator", fitted to
# sin x), an instance of it with fewer samples, a method factory, and a module that fails.
SOURCE = '''
"""A throwaway physgrad plugin."""
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

import physgrad
from physgrad.methods import Gradient, Method


class Doubled(physgrad.AbstractProblem):
    """Fit sin x through a simulator that doubles the network's output."""

    n_train: int = eqx.field(static=True, default=64)
    n_test: int = eqx.field(static=True, default=32)
    gain: float = eqx.field(static=True, default=2.0)

    name: ClassVar[str] = "doubled"
    source: ClassVar[str] = "a test"
    default_batch_size: ClassVar[int] = 16

    def make_data(self, key):
        k1, k2 = jax.random.split(key)
        return {"train": {"x": jax.random.uniform(k1, (self.n_train, 1))},
                "test": {"x": jax.random.uniform(k2, (self.n_test, 1))}}

    def make_network(self, key):
        return eqx.nn.MLP(1, 1, 4, 1, key=key)

    def network_output(self, network, sample):
        return network(sample["x"])

    def simulate(self, x, sample):
        return self.gain * x

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - jnp.sin(sample["x"])) ** 2)


SMALL = Doubled(n_train=24, gain=3.0)


def small():
    return Doubled(n_train=20)


def demo_sgd(*, lr: float = 0.05, momentum: float = 0.0):
    """SGD on DP gradients, from a plugin."""
    return Method(Gradient(), optax.sgd(lr, momentum=momentum or None))


def needs_argument(lr):
    return demo_sgd(lr=lr)
'''

ENTRY_POINTS = f"""
[physgrad.problems]
doubled_demo = {PACKAGE}:Doubled
broken_demo = {PACKAGE}.broken:Thing
hig_toy = {PACKAGE}:Doubled

[physgrad.methods]
demo_sgd = {PACKAGE}:demo_sgd
"""


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """The throwaway package on sys.path with its dist-info; the registries read it afresh
    and forget it afterwards."""
    site = tmp_path / "site"
    (site / PACKAGE).mkdir(parents=True)
    (site / PACKAGE / "__init__.py").write_text(SOURCE)
    (site / PACKAGE / "broken.py").write_text("raise ImportError('this plugin is broken on purpose')\n")
    info = site / f"{PACKAGE}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {PACKAGE}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(ENTRY_POINTS)
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.chdir(tmp_path)
    for table in (PROBLEMS, METHODS):
        table.reload_plugins()
    yield tmp_path
    for table in (PROBLEMS, METHODS):
        table.reload_plugins()
    for name in [m for m in sys.modules if m == PACKAGE or m.startswith(PACKAGE + ".")]:
        del sys.modules[name]


def run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def summary(run_dir):
    return json.loads((run_dir / "summary.json").read_text())


def test_train_by_import_path(plugin, capsys):
    code, out, err = run(["train", f"{PACKAGE}:Doubled", "--method", "hig", "--steps", "3", "--quiet"], capsys)
    assert code == 0, err
    run_dir = plugin / "runs" / f"{PACKAGE}.Doubled-hig-seed0"  # the colon left out of the file name
    assert summary(run_dir)["steps"] == 3
    assert json.loads((run_dir / "config.json").read_text())["problem"] == f"{PACKAGE}:Doubled"


def test_train_by_entry_point_with_a_plugin_method(plugin, capsys):
    argv = ["train", "doubled_demo", "--method", "demo_sgd", "--steps", "2", "--set", "lr=0.1", "--quiet"]
    code, out, err = run(argv, capsys)
    assert code == 0, err
    assert summary(plugin / "runs" / "doubled_demo-demo_sgd-seed0")["steps"] == 2
    # a sequence of a plugin method by import path, then HIG: the path keeps its colon
    argv = ["train", "doubled_demo", "--method", f"{PACKAGE}:demo_sgd:2,hig", "--steps", "3", "--quiet"]
    code, out, err = run(argv, capsys)
    assert code == 0, err


def test_list_shows_plugins_and_one_line_for_a_broken_one(plugin, capsys):
    code, out, err = run(["list"], capsys)
    assert code == 0
    assert "doubled_demo" in out and "Fit sin x through a simulator" in out
    assert "demo_sgd" in out and "SGD on DP gradients, from a plugin." in out
    assert "oscillators" in out and "hig_toy" in out  # the built-in list is whole
    assert err == ""  # the plugins left out are listed, one line each, not warned about as well
    broken = [line for line in out.splitlines() if "broken_demo" in line]
    assert len(broken) == 1 and "this plugin is broken on purpose" in broken[0]
    taken = [line for line in out.splitlines() if "'hig_toy' is a built-in name" in line]
    assert len(taken) == 1
    assert PROBLEMS["hig_toy"].__module__ == "physgrad.problems.hig_toy"  # the built-in kept its name


@pytest.mark.parametrize(
    ("problem", "line"),
    [
        ("no_such_module_xyz:Thing", "no module named 'no_such_module_xyz'"),
        (f"{PACKAGE}:Nothing", f"module '{PACKAGE}' has no attribute 'Nothing'"),
        (f"{PACKAGE}:demo_sgd", "the function returned a Method, not a physgrad.AbstractProblem"),
        (f"{PACKAGE}:ENTRY", "not a physgrad.AbstractProblem subclass"),
        ("broken_demo", "this plugin is broken on purpose"),
        (f"{PACKAGE}.broken:Thing", "importing physgrad_demo_plugin.broken failed (ImportError: this plugin"),
    ],
)
def test_bad_problems_are_one_line_with_status_2(plugin, capsys, problem, line):
    (plugin / "site" / PACKAGE / "__init__.py").write_text(SOURCE + "\nENTRY = 3\n")
    code, out, err = run(["train", problem, "--method", "adam", "--steps", "1"], capsys)
    assert code == 2
    assert "Traceback" not in err
    errors = [e for e in err.splitlines() if e.startswith("physgrad: error:")]
    assert len(errors) == 1 and line in errors[0]
    # the plugins left out are warning lines beside it, each one line
    assert all(e.startswith("physgrad: warning: plugin") for e in err.splitlines() if e not in errors)


def test_bad_method_factories(plugin, capsys):
    code, out, err = run(["train", "hig_toy", "--method", f"{PACKAGE}:needs_argument", "--steps", "1"], capsys)
    assert code == 2 and "parameter 'lr' needs a default" in err
    with pytest.raises(ConfigError, match="defaults to a list"):
        method_factory(lambda *, sizes=[1]: None, "m")  # noqa: B006
    factory = method_factory(lambda *, lr=1.0: "not a method", "m")
    with pytest.raises(ConfigError, match="returned a str, not a physgrad.methods.AbstractMethod"):
        factory(lr=0.5)


@pytest.mark.filterwarnings("ignore::physgrad.harness.plugins.PluginWarning")
def test_an_instance_or_a_function_gives_the_settings_defaults(plugin):
    import physgrad_demo_plugin as demo  # pyright: ignore[reportMissingImports]

    from physgrad.harness.config import valid_settings

    assert is_import_path(f"{PACKAGE}:SMALL") and not is_import_path("adam:2000")
    settings = valid_settings(f"{PACKAGE}:SMALL", "adam")
    assert (settings["n_train"], settings["n_test"], settings["gain"]) == (24, 32, 3.0)
    assert valid_settings(f"{PACKAGE}:small", "adam")["n_train"] == 20
    cls = problem_class(demo.SMALL, "x")
    assert issubclass(cls, demo.Doubled) and cls().gain == 3.0 and cls(gain=1.0).gain == 1.0
    assert problem_class(demo.Doubled, "x") is demo.Doubled  # a class with its own name is itself


def docs_blocks() -> dict[str, str]:
    """docs/own-problem.md's Python blocks by the file name their first line gives."""
    text = (Path(__file__).parents[1] / "docs" / "own-problem.md").read_text()
    blocks = re.findall(r"```python\n# (\S+)\n(.*?)```", text, re.S)
    return {name: code for name, code in blocks}


def test_the_docs_example_trains_from_the_working_directory(plugin, capsys, monkeypatch):
    # `physgrad` the script does not put the working directory on sys.path (python -m does)
    here = plugin / "work"
    here.mkdir()
    blocks = docs_blocks()
    assert set(blocks) == {"spring.py", "my_rules.py"}
    for name, code in blocks.items():
        (here / name).write_text(code)
    monkeypatch.chdir(here)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", ".", str(here))])
    try:
        argv = ["train", "spring:Launch", "--method", "my_rules:hig_adam", "--steps", "2", "--quiet",
                "--set", "n_train=32", "--set", "n_test=16", "--set", "n_steps=10"]  # fmt: skip
        code, out, err = run(argv, capsys)
        assert code == 0, err
        assert summary(here / "runs" / "spring.Launch-my_ruleshig_adam-seed0")["steps"] == 2
        # the page's error lines are what the command line prints
        text = (Path(__file__).parents[1] / "docs" / "own-problem.md").read_text()
        for problem in ("sprng:Launch", "spring:Lunch", "spring:jax"):
            code, out, err = run(["train", problem, "--method", "adam", "--steps", "1"], capsys)
            line = [e for e in err.splitlines() if e.startswith("physgrad: error:")]
            assert code == 2 and len(line) == 1 and line[0] in text, err
    finally:
        for name in ("spring", "my_rules"):
            sys.modules.pop(name, None)


def test_a_library_user_sees_a_warning_not_an_error(plugin):
    table = Registry("problem", {}, "physgrad.problems", problem_class)
    with pytest.warns(PluginWarning, match="broken_demo"):
        names = list(table)
    assert "doubled_demo" in names and "broken_demo" not in names
    assert table.why_not("broken_demo") == table.left_out["broken_demo"]


def wheel(directory: Path) -> Path:
    """The throwaway package as a wheel, zipped by hand (no build backend is needed offline)."""
    info = f"{PACKAGE}-0.1.dist-info"
    files = {
        f"{PACKAGE}/__init__.py": SOURCE,
        f"{info}/METADATA": f"Metadata-Version: 2.1\nName: {PACKAGE}\nVersion: 0.1\n",
        f"{info}/WHEEL": "Wheel-Version: 1.0\nGenerator: physgrad-tests\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
        f"{info}/entry_points.txt": ENTRY_POINTS.replace(f"broken_demo = {PACKAGE}.broken:Thing\n", ""),
    }
    record = []
    for name, text in files.items():
        digest = base64.urlsafe_b64encode(hashlib.sha256(text.encode()).digest()).rstrip(b"=").decode()
        record.append(f"{name},sha256={digest},{len(text.encode())}")
    files[f"{info}/RECORD"] = "\n".join([*record, f"{info}/RECORD,,"]) + "\n"
    path = directory / f"{PACKAGE}-0.1-py3-none-any.whl"
    with zipfile.ZipFile(path, "w") as archive:
        for name, text in files.items():
            archive.writestr(name, text)
    return path


@pytest.mark.slow  # pip and a venv (tens of seconds); the fast tests above cover the same lookups
def test_pip_installed_package_trains_by_entry_point(tmp_path):
    env = tmp_path / "venv"
    venv.create(env, with_pip=False)
    python = env / "bin" / "python"
    # this interpreter's packages (physgrad, JAX, ...) seen from the new venv, as
    # --system-site-packages would where this interpreter is itself a venv's
    target = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"],
                            capture_output=True, text=True, check=True).stdout.strip()  # fmt: skip
    (Path(target) / "parent.pth").write_text("\n".join(p for p in sys.path if p and Path(p).is_dir()) + "\n")
    install = [sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q",
               wheel(tmp_path)]  # fmt: skip
    installed = subprocess.run(install, capture_output=True, text=True, timeout=300)
    assert installed.returncode == 0, installed.stderr[-3000:]
    train = [python, "-m", "physgrad", "train", "doubled_demo", "--method", "demo_sgd", "--steps", "2", "--quiet",
             "--out", tmp_path / "run"]  # fmt: skip
    result = subprocess.run(train, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert summary(tmp_path / "run")["steps"] == 2
    listing = subprocess.run([python, "-m", "physgrad", "list"], capture_output=True, text=True, timeout=300)
    assert f"(plugin: {PACKAGE})" in listing.stdout
