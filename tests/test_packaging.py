"""Package metadata: one version, the license file and py.typed in the wheel, extras, floors."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest

import physgrad

ROOT = Path(__file__).parent.parent
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_version_flag_prints_the_package_version():
    result = subprocess.run(
        [sys.executable, "-m", "physgrad", "--version"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"physgrad {physgrad.__version__}"


def test_the_version_is_written_in_one_place():
    project = PYPROJECT["project"]
    assert "version" not in project and "version" in project["dynamic"]
    assert PYPROJECT["tool"]["hatch"]["version"]["path"] == "src/physgrad/__init__.py"
    assert re.fullmatch(r"\d+\.\d+\.\d+\S*", physgrad.__version__)
    try:
        installed = version("physgrad")
    except PackageNotFoundError:  # run from a source tree without installing
        pytest.skip("physgrad is not installed")
    assert installed == physgrad.__version__


def test_the_wheel_carries_the_license_and_py_typed():
    """What hatchling puts in the wheel: the package directory (so its py.typed marker) and
    the license files of PEP 639 (checked on a built wheel by hand: LICENSE under
    .dist-info/licenses/, physgrad/py.typed)."""
    project = PYPROJECT["project"]
    assert project["license"] == "Apache-2.0" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").read_text().split()[:4] == ["Apache", "License", "Version", "2.0,"]
    assert (ROOT / "src/physgrad/py.typed").exists()
    assert PYPROJECT["tool"]["hatch"]["build"]["targets"]["wheel"]["packages"] == ["src/physgrad"]
    hatchling = next(r for r in PYPROJECT["build-system"]["requires"] if r.startswith("hatchling"))
    assert tuple(map(int, hatchling.split(">=")[1].split("."))) >= (1, 27)  # PEP 639 support
    assert "Typing :: Typed" in project["classifiers"]


def test_the_metadata_names_authors_keywords_and_a_posix_system():
    """physgrad.engine.rundir locks run directories with fcntl (POSIX only), so no "OS Independent"."""
    project = PYPROJECT["project"]
    assert project["authors"] == [{"name": "physgrad developers"}] and len(project["keywords"]) >= 5
    assert "Operating System :: POSIX" in project["classifiers"]
    assert not any("OS Independent" in c for c in project["classifiers"])
    for name in ("CITATION.cff", "CONTRIBUTING.md", "CHANGELOG.md", ".pre-commit-config.yaml"):
        assert (ROOT / name).is_file(), name
    assert f"version: {physgrad.__version__}" in (ROOT / "CITATION.cff").read_text()
    assert "## 0.1.0" in (ROOT / "CHANGELOG.md").read_text() or physgrad.__version__ != "0.1.0"


def test_the_sdist_leaves_out_the_study_data():
    exclude = PYPROJECT["tool"]["hatch"]["build"]["targets"]["sdist"]["exclude"]
    assert {"/docs/reproductions/data", "/docs/reproductions/figures", "/docs/benchmark/*/*/runs"} <= set(exclude)


def requirement(spec: str) -> tuple[str, str]:
    name, _, bound = re.match(r"([A-Za-z0-9_.\-]+)(\[[^\]]*\])?(.*)", spec).groups()
    return name.lower(), bound


def test_optional_packages_are_extras_and_every_floor_is_pinned_by_make_test_floors():
    project = PYPROJECT["project"]
    core = dict(requirement(r) for r in project["dependencies"])
    extras = project["optional-dependencies"]
    assert "kfac-jax" not in core and "exponax" not in core and "jaxtyping" in core
    assert extras["kfac"] == ["kfac-jax>=0.0.8,<0.0.9"]  # kfac.py patches a private kfac-jax function
    assert [requirement(r)[0] for r in extras["pde"]] == ["exponax"]
    assert extras["all"] == ["physgrad[kfac,pde,phiflow,postgres,tensorboard]"]
    # physgrad.problems.sim.phiflow subclasses a private PhiML class: phiml below its next minor version
    phiml = dict(requirement(r) for r in extras["phiflow"])["phiml"]
    assert re.fullmatch(r">=1\.16\.0,<1\.17", phiml), phiml
    assert "optuna" in core and "distributed" in core  # tune and the workers need nothing extra
    # every lower bound of the core and of the extras is a version `make test-floors` installs
    makefile = (ROOT / "Makefile").read_text()
    pinned = dict(re.findall(r"([A-Za-z0-9_.\-]+)==([0-9][0-9A-Za-z.]*)", makefile))
    pinned = {k.lower(): v for k, v in pinned.items()}
    for spec in (project["dependencies"] + extras["kfac"] + extras["pde"] + extras["phiflow"] + extras["tensorboard"]
                 + extras["postgres"]):  # fmt: skip
        name, bound = requirement(spec)
        floor = re.search(r">=([0-9][0-9A-Za-z.]*)", bound).group(1)
        assert pinned.get(name) == floor, f"{name}: floor {floor}, make test-floors pins {pinned.get(name)}"
