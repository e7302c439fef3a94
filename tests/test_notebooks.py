"""The example notebooks (examples/*.ipynb) run from top to bottom without an error.

The slow tier (``make test-slow``, ``make test-all``): each notebook is executed by nbclient
in a fresh kernel of this interpreter, on a copy (the committed outputs are not rewritten),
with a time limit per notebook. The kernel imports this checkout's physgrad (``src`` is put
first on its ``PYTHONPATH``) and writes generated data to a temporary ``PHYSGRAD_CACHE``.
A notebook whose extra is not installed is skipped. Re-executing and committing a
notebook's outputs: ``python -m tests.test_notebooks examples/NAME.ipynb`` (in place).
"""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
NOTEBOOKS = sorted(EXAMPLES.glob("*.ipynb"))
TIMEOUT = 600  # seconds per cell; a notebook takes one to three minutes on one loaded core
SESSION_ONLY_FLAGS = (
    "--xla_backend_optimization_level",
    "--xla_llvm_disable_expensive_passes",
    "--xla_cpu_use_fusion_emitters",
    "--xla_force_host_platform_device_count",
)
NEEDS = {  # notebook -> modules of its extra
    "01_hig_lm_kfac_own_loop.ipynb": ("kfac_jax",),
    "04_time_stepper_exponax.ipynb": ("exponax",),
    "05_phiflow.ipynb": ("phi", "phiml"),
}


def execute(path: Path, env: dict[str, str] | None = None, timeout: int = TIMEOUT):
    """The notebook at ``path`` executed in a fresh python3 kernel from its own folder;
    returns the executed notebook (raises nbclient's CellExecutionError on an error)."""
    import nbformat
    from nbclient import NotebookClient

    notebook = nbformat.read(path, as_version=4)
    saved = dict(os.environ)
    os.environ.update(env or {})
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), *filter(None, [saved.get("PYTHONPATH")])])
    # XLA's own defaults for the kernel: not the test session's compile-time flags from
    # conftest.py (optimisation level 0 made notebook 04's convolutions several times slower
    # and ran it past the time limit) nor its four simulated devices
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(SESSION_ONLY_FLAGS)]
    os.environ["XLA_FLAGS"] = " ".join(flags)
    try:
        client = NotebookClient(notebook, timeout=timeout, kernel_name="python3",
                                resources={"metadata": {"path": str(path.parent)}})  # fmt: skip
        client.execute()
    finally:
        os.environ.clear()
        os.environ.update(saved)
    return notebook


def test_the_examples_folder_lists_every_notebook():
    assert len(NOTEBOOKS) >= 5
    readme = (EXAMPLES / "README.md").read_text()
    for path in NOTEBOOKS:
        assert path.name in readme, f"examples/README.md does not list {path.name}"


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    pytest.importorskip("nbclient", reason="executing notebooks needs nbclient (the test extra)")
    pytest.importorskip("ipykernel", reason="executing notebooks needs ipykernel (the test extra)")
    for module in NEEDS.get(path.name, ()):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{path.name} needs {module}")
    notebook = execute(
        path, env={"PHYSGRAD_CACHE": str(tmp_path / "cache"), "MPLBACKEND": "module://matplotlib_inline.backend_inline"}
    )
    errors = [
        o for c in notebook.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"
    ]
    assert not errors


if __name__ == "__main__":  # re-execute notebooks in place: python -m tests.test_notebooks examples/NAME.ipynb ...
    import nbformat

    for name in sys.argv[1:]:
        start = time.perf_counter()
        executed = execute(Path(name).resolve())
        nbformat.write(executed, name)
        print(f"{name}: {time.perf_counter() - start:.0f} s")
