"""Generated datasets cached on disk, so a problem's expensive reference simulations run once.

Files live in ``$PHYSGRAD_CACHE`` (default ``~/.cache/physgrad``), one ``.npz`` per dataset,
named by the problem and a hash of everything that changes the data (settings, seed,
generator version). A file is written whole (:func:`physgrad.engine.rundir.atomic_file`: a
temporary name, flushed, renamed), so an interrupted or failed write never leaves a
truncated dataset behind, and it carries a manifest (each array's name and sha256): a cached
file that is truncated, empty, changed or missing an array is not used but generated again,
with a one-line note.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ...errors import ConfigError

MANIFEST = "__physgrad_manifest__"  # the array holding each array's sha256 (JSON text)


def cache_dir() -> Path:
    """Where generated datasets are cached (``$PHYSGRAD_CACHE`` or ``~/.cache/physgrad``)."""
    return Path(os.environ.get("PHYSGRAD_CACHE", Path.home() / ".cache" / "physgrad"))


def _usable_dir() -> Path:
    """The cache directory, refused in one line (before minutes of generation) if it names
    a file or cannot be made."""
    directory = cache_dir()
    if directory.exists() and not directory.is_dir():
        raise ConfigError(f"PHYSGRAD_CACHE names a file ({directory}), not a directory; point it at a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"the dataset cache {directory} cannot be made ({e.strerror or e}); set PHYSGRAD_CACHE "
                          "to a writable directory") from None  # fmt: skip
    return directory


def _digest(array: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def _read(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a cached file, verified against its manifest; ValueError naming what is
    wrong (a file of an older physgrad, without a manifest, is read as it is)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as e:  # noqa: BLE001 — truncated, empty, not a zip, a bad CRC: all mean "damaged"
        raise ValueError(f"it cannot be read ({type(e).__name__})") from None
    if MANIFEST not in arrays:
        return arrays
    try:
        manifest = json.loads(str(arrays.pop(MANIFEST)))
    except ValueError:
        raise ValueError("its manifest is not valid JSON") from None
    missing = sorted(set(manifest) - set(arrays))
    if missing:
        raise ValueError(f"the array {missing[0]!r} is missing")
    changed = sorted(k for k, digest in manifest.items() if _digest(arrays[k]) != digest)
    if changed:
        raise ValueError(f"the array {changed[0]!r} does not match its checksum")
    return arrays


def cached_arrays(stem: str, key: dict, generate: Callable[[], dict]) -> dict[str, np.ndarray]:
    """``generate()``'s arrays, from ``<stem>-<hash(key)>.npz`` when it exists and verifies,
    else generated and saved there. ``key`` must hold every input that changes the data
    (JSON-serialisable)."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]
    directory = _usable_dir()
    path = directory / f"{stem}-{digest}.npz"
    if path.exists():
        try:
            return _read(path)
        except ValueError as e:
            print(f"physgrad: the cached dataset {path} is damaged ({e}); generating it again", file=sys.stderr)
    data = {k: np.asarray(v) for k, v in generate().items()}
    manifest = json.dumps({k: _digest(v) for k, v in data.items()}, sort_keys=True)
    from ...engine.rundir import atomic_file

    with atomic_file(path) as f:  # a failed write (a full disk) leaves no temporary file behind
        np.savez(f, **data, **{MANIFEST: np.array(manifest)})  # pyright: ignore[reportArgumentType]
    return data
