"""What physgrad asks of its platform and its dependencies (issue 53, item 5): a system
without ``fcntl`` gets one line where a run directory is locked, not an ImportError; the
private PhiML class ``physgrad.problems.sim.phiflow`` subclasses is pinned below PhiML's next
minor version, and the installed PhiML is inside the bound."""

import sys
import tomllib
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

from physgrad.engine import rundir
from physgrad.errors import ConfigError

ROOT = Path(__file__).parents[1]


def test_no_fcntl_is_one_line_and_leaves_no_directory(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "fcntl", None)  # `import fcntl` raises ImportError, as on Windows
    target = tmp_path / "runs" / "one"
    with pytest.raises(ConfigError) as info, rundir.one_writer(target):
        pass
    line = str(info.value)
    assert "\n" not in line and "fcntl.flock" in line and "Linux or macOS" in line and "out=None" in line
    assert not (tmp_path / "runs").exists()  # made for the lock, removed again
    assert "Operating System :: POSIX" in (ROOT / "pyproject.toml").read_text()


def test_phiml_is_bounded_below_its_next_minor_version():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    phiml = [Requirement(r) for group in extras.values() for r in group if Requirement(r).name == "phiml"]
    assert phiml, "no phiml requirement"
    for requirement in phiml:
        uppers = [Version(s.version) for s in requirement.specifier if s.operator == "<"]
        lowers = [Version(s.version) for s in requirement.specifier if s.operator == ">="]
        assert len(uppers) == 1 and len(lowers) == 1, str(requirement)
        upper, lower = uppers[0], lowers[0]
        # below the next minor version of the lowest supported one: 1.16.x -> < 1.17
        assert (upper.major, upper.minor, upper.micro) == (lower.major, lower.minor + 1, 0), str(requirement)
    try:
        installed = version("phiml")
    except PackageNotFoundError:
        pytest.skip("phiml is not installed (the phiflow extra)")
    assert all(installed in r.specifier for r in phiml), installed
