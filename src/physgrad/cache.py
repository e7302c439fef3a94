"""Generated datasets cached on disk, so a problem's expensive reference simulations run once.

Files live in ``$PHYSGRAD_CACHE`` (default ``~/.cache/physgrad``), one ``.npz`` per dataset,
named by the problem and a hash of everything that changes the data (settings, seed,
generator version). A file is written under a temporary name and renamed, so a run that
is interrupted while writing never leaves a truncated dataset behind.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np


def cache_dir() -> Path:
    """Where generated datasets are cached (``$PHYSGRAD_CACHE`` or ``~/.cache/physgrad``)."""
    return Path(os.environ.get("PHYSGRAD_CACHE", Path.home() / ".cache" / "physgrad"))


def cached_arrays(stem: str, key: dict, generate: Callable[[], dict]) -> dict[str, np.ndarray]:
    """``generate()``'s arrays, from ``<stem>-<hash(key)>.npz`` when it exists, else generated
    and saved there. ``key`` must hold every input that changes the data (JSON-serialisable)."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]
    path = cache_dir() / f"{stem}-{digest}.npz"
    if path.exists():
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    data = {k: np.asarray(v) for k, v in generate().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **data)  # pyright: ignore[reportArgumentType]  # numpy's stub lets **kwds fill allow_pickle
    os.replace(tmp, path)
    return data
