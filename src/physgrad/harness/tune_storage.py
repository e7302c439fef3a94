"""Where a tuning keeps its trials and how it draws them: Optuna's journal file in the study
directory by default (safe for many local workers, survives kill -9), a storage URL
(PostgreSQL for many machines) or a storage object; scrambled Sobol points
(:mod:`physgrad.harness.tune`)."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

from ..errors import ConfigError

JOURNAL = "optuna.journal"


def open_storage(out: Path, storage: Any = None):
    """The Optuna storage: the journal file ``out/optuna.journal`` by default (Optuna ≥ 4:
    ``JournalFileBackend``; earlier: ``JournalFileStorage``), a storage URL (``postgresql://…``,
    ``sqlite:///…``) as an ``RDBStorage``, or a storage object as it is."""
    import optuna

    if storage is None:
        journal = getattr(optuna.storages, "journal", None)
        backend = getattr(journal, "JournalFileBackend", None) or optuna.storages.JournalFileStorage
        return optuna.storages.JournalStorage(backend(str(out / JOURNAL)))
    if isinstance(storage, str):
        return optuna.storages.RDBStorage(_with_driver(storage))
    return storage


def _with_driver(url: str) -> str:
    """A ``postgresql://`` URL with the PostgreSQL driver that is installed (SQLAlchemy 2.0
    defaults to psycopg2, 2.1 to psycopg 3; ``physgrad[postgres]`` installs psycopg2)."""
    import importlib.util

    if not url.startswith("postgresql://"):
        return url
    for module, dialect in (("psycopg", "psycopg"), ("psycopg2", "psycopg2")):
        if importlib.util.find_spec(module) is not None:
            return f"postgresql+{dialect}://" + url[len("postgresql://") :]
    raise ConfigError("a postgresql:// storage needs a PostgreSQL driver: pip install 'physgrad[postgres]'")


def default_sampler(seed: int = 0):
    """Scrambled Sobol points (``QMCSampler``), seeded: trial k's point is the same in every run."""
    import optuna

    with warnings.catch_warnings():  # "QMCSampler is experimental": it is the protocol's sampler
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.samplers.QMCSampler(qmc_type="sobol", scramble=True, seed=seed, warn_independent_sampling=False)


__all__ = ["JOURNAL", "default_sampler", "open_storage"]
