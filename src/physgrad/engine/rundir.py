"""The files of run and study directories, written so that a kill at any moment never loses
or corrupts a result (they are what people cite).

- :func:`atomic_write`: a file is written aside, flushed to disk and renamed into place, so a
  reader (or a resumed run) sees the old content or the new one, never half of either.
- :func:`one_writer`: an OS file lock (``fcntl.flock`` on ``DIR/.lock``) held for the life
  of a run or study; a second writer is refused in one line naming the holder (pid, host,
  command). The OS drops the lock when its process dies, so a killed run never leaves a
  stale lock behind.
- :func:`save_checkpoint` / :func:`load_checkpoint`: a checkpoint is one directory,
  ``checkpoint/`` (``state.eqx``, ``counters.json``, ``manifest.json``), written aside as
  ``checkpoint.new/``, flushed, and swapped in by two renames (the previous one goes to
  ``checkpoint.old/`` for the instant between them, and is read if a kill lands there).
  ``manifest.json`` (format version, step, each file's size and sha256) is written last and
  verified on load, so a truncated file, flipped bits, a missing file or a torn checkpoint
  is one line saying what is wrong, never a silently wrong resume. A checkpoint of an older
  physgrad (no manifest) still loads, unverified: it predates the checksums.
- :func:`fault`: a **test-only** hook. ``PHYSGRAD_TEST_FAULT="POINT:kill"`` (or
  ``POINT:kill@N`` for the N-th time the point is passed, or ``POINT:sleep:SECONDS``; several
  comma-separated) kills or pauses the process at a named point, so tests/test_faults.py can
  land a SIGKILL between two writes deterministically. Unset (always, outside tests) it does
  nothing. Points: ``step`` (after each training step), ``checkpoint-written`` (the new
  checkpoint complete aside), ``checkpoint-aside`` (the previous one moved aside, the new one
  not yet in place), ``checkpoint-committed``, ``before-summary`` (the final checkpoint written,
  ``params.eqx`` and ``summary.json`` not yet), ``evaluating`` (an evaluation begins), ``calibrating`` (a study's calibration begins). Action
  ``term`` sends the process SIGTERM, ``int`` SIGINT (Ctrl-C).

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import signal
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from ..errors import ConfigError

LOCK_NAME = ".lock"
CHECKPOINT = "checkpoint"
CHECKPOINT_FORMAT = 1  # manifest.json's "format"; a newer one is refused, not guessed at
FAULT_VARIABLE = "PHYSGRAD_TEST_FAULT"


# --- atomic files ------------------------------------------------------------------------------
def fsync_directory(directory: Path) -> None:
    """Make a rename inside ``directory`` durable (a no-op where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_synced(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[IO[bytes]]:
    """A binary file to write ``path`` through, all at once: the body writes a temporary
    file beside it, which is flushed to disk and renamed over ``path`` when the body
    returns (a reader sees the old file or the new one). If the body or the write fails
    (a full disk, a kill's KeyboardInterrupt), the temporary file is removed and ``path``
    is left as it was. The one writer of every file physgrad writes whole: run files,
    tables, figures (``savefig(f)``), calibration records, cached datasets."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        if e.filename is None:  # a failed write() names no file: name the one being written
            raise OSError(e.errno, e.strerror, str(path)) from None
        raise
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise
    fsync_directory(path.parent)


def atomic_write(path: str | Path, data: bytes | str) -> None:
    """Replace ``path`` by ``data`` all at once (:func:`atomic_file`)."""
    with atomic_file(path) as f:
        f.write(data.encode() if isinstance(data, str) else data)


def json_text(data: Any) -> str:
    """How run directories write JSON (sorted keys, so equal data give equal bytes)."""
    return json.dumps(data, indent=2, sort_keys=True, default=str) + "\n"


# What :func:`read_json`'s one line advises for a study's own files and for a run's files.
NOT_A_STUDY = ("not a physgrad study, sweep or bench directory, or a damaged one: re-draw from a complete copy, "
               "or run the study again")  # fmt: skip
RUN_DAMAGED = "the run is damaged: remove its directory and run the study again to re-run it"


def read_json(path: str | Path, advice: str, *, empty: Any = None) -> Any:
    """The JSON object in ``path`` (``empty`` where the file does not exist, if given); a
    missing, unreadable or damaged file, or one that holds no JSON object, is one
    :class:`ConfigError` line naming the file, what is wrong and ``advice``."""
    path = Path(path)
    if empty is not None and not path.exists():
        return empty
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path} is missing; {advice}") from None
    except (OSError, ValueError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else "not valid JSON"
        raise ConfigError(f"{path} is damaged ({why}); {advice}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} is damaged (not a JSON object); {advice}")
    return data


def strict_json_text(data: Any) -> str:
    """:func:`json_text` that strict JSON parsers accept: a NaN or infinite number (a
    diverged run's loss) is written as ``null``, since JSON has no such numbers."""
    return json.dumps(finite_or_none(data), indent=2, sort_keys=True, default=str, allow_nan=False) + "\n"


def finite_or_none(data: Any) -> Any:
    """``data`` with every non-finite float replaced by None (dicts, lists and tuples walked)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: finite_or_none(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_or_none(v) for v in data]
    return data


# --- one writer --------------------------------------------------------------------------------
def _holder(fd: int) -> str:
    try:
        info = json.loads(os.pread(fd, 65536, 0).decode())
        return f"pid {info['pid']} on {info['host']} since {info['since']} ({info['command']})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


def _created_dirs(directory: Path) -> list[Path]:
    """Make ``directory`` (and missing parents); the ones made, deepest first."""
    missing = [d for d in (directory, *directory.parents) if not d.exists()]
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot write to {directory}: {e.strerror or e}") from None
    return missing


@contextlib.contextmanager
def one_writer(directory: str | Path, what: str = "run", enabled: bool = True) -> Iterator[None]:
    """Hold ``DIRECTORY/.lock`` (an exclusive ``flock``) while the body runs; a second writer
    of the same directory gets a one-line ConfigError naming the holder.

    The directory is made if missing, and removed again if the body leaves it empty (a run
    refused before writing anything leaves no files). The lock file is removed on release,
    so a finished run's directory is as it was; the OS releases the lock of a killed
    process, whose stale ``.lock`` the next writer simply takes over. ``enabled=False``
    (the processes of a multi-process run other than the writer) holds nothing."""
    if not enabled:
        yield
        return
    directory = Path(directory)
    created = _created_dirs(directory)
    path = directory / LOCK_NAME
    try:
        fd = _acquire(path, directory, what)
    except BaseException:
        _remove_empty(created)
        raise
    try:
        yield
    finally:
        with contextlib.suppress(OSError):  # a read-only or full disk: the OS lock goes with the descriptor
            path.unlink(missing_ok=True)  # while holding the lock: a waiter re-checks the inode
        os.close(fd)
        with contextlib.suppress(OSError):
            _remove_empty(created)


def _acquire(path: Path, directory: Path, what: str) -> int:
    try:  # POSIX only (the package's classifier says so): elsewhere one line, not an ImportError
        import fcntl
    except ImportError:
        raise ConfigError(f"cannot lock {directory}: run and study directories are locked with fcntl.flock, which "
                          f"this system ({sys.platform}) lacks; physgrad's run directories need Linux or macOS "
                          "(on Windows: WSL), or train in memory (physgrad.fit with out=None)") from None  # fmt: skip

    while True:
        if path.is_symlink():  # never write through a link someone left in our place
            raise ConfigError(f"{path} is a symbolic link, not physgrad's lock file; remove it (physgrad never "
                              "follows a link there) and run again")  # fmt: skip
        try:  # O_NOFOLLOW: a link made between the check and the open is refused too
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as e:
            if path.is_symlink():
                raise ConfigError(
                    f"{path} is a symbolic link, not physgrad's lock file; remove it and run again"
                ) from None
            raise ConfigError(f"cannot write to {directory}: {e.strerror or e}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = _holder(fd)
            os.close(fd)
            raise ConfigError(
                f"{directory} is in use by another {what} ({holder}); wait for it to finish or stop it, "
                "or choose another directory"
            ) from None
        try:  # the holder before us may have removed the file we opened: lock the current one
            current = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            current = False
        if current:
            break
        os.close(fd)
    info = {"pid": os.getpid(), "host": socket.gethostname(), "command": _command(),
            "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")}  # fmt: skip
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(info).encode(), 0)
    return fd


def _command() -> str:
    """This process's command line as a user typed it (``physgrad train ...``)."""
    argv = list(sys.argv) or ["python"]
    program = Path(argv[0])
    argv[0] = program.parent.name if program.name == "__main__.py" else program.name
    return " ".join(argv)


def _remove_empty(created: list[Path]) -> None:
    for d in created:  # deepest first; stops at the first that holds something
        try:
            d.rmdir()
        except OSError:
            return


# --- SIGTERM as Ctrl-C ---------------------------------------------------------------------------
class Terminated(KeyboardInterrupt):
    """SIGTERM (what schedulers and ``kill`` send), raised where Ctrl-C would be, so a
    terminated run checkpoints and stops the same way."""


def _raise_terminated(signum, frame):
    raise Terminated


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` (a KeyboardInterrupt) while the body runs; the
    previous handler is restored after. Only the main thread may set handlers: elsewhere
    (a run started in a thread) this does nothing."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class deferred_interrupts(contextlib.AbstractContextManager):
    """Ctrl-C and SIGTERM wait until the body is done, then stop the run as usual.

    The loop's bookkeeping after a chunk (the state's counters, an evaluation logged to
    ``metrics.csv``, the checkpoint after it) is one unit: a signal that lands inside it
    would stop the run with a step taken whose evaluation was never logged, and a resume
    would go on without it. Inside the body a signal is remembered and raised
    (:class:`KeyboardInterrupt` or :class:`Terminated`) when the body ends; a second
    Ctrl-C raises at once (the user insists; that evaluation is then made again by no one).
    Outside the main thread it does nothing, and a signal whose handler is not one that
    raises (Python's Ctrl-C, :func:`terminate_as_interrupt`'s SIGTERM) is left alone."""

    def __init__(self):
        self.pending: int | None = None
        self.previous: dict[int, Any] = {}

    def _remember(self, signum, frame):
        if signum == signal.SIGINT and self.pending == signal.SIGINT:
            raise KeyboardInterrupt
        self.pending = signum

    def __enter__(self):
        import threading

        if threading.current_thread() is threading.main_thread():
            # only the signals that would raise here (Ctrl-C's default, SIGTERM inside
            # terminate_as_interrupt): a handler of the user's own is left alone
            raising = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: _raise_terminated}
            for signum, handler in raising.items():
                if signal.getsignal(signum) is handler:
                    self.previous[signum] = signal.signal(signum, self._remember)
        return self

    def __exit__(self, *exc):
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        if self.pending is not None and exc[0] is None:
            raise Terminated if self.pending == signal.SIGTERM else KeyboardInterrupt
        return None


# --- checkpoints -------------------------------------------------------------------------------
def _aside(run_dir: Path) -> tuple[Path, Path, Path]:
    return run_dir / CHECKPOINT, run_dir / f"{CHECKPOINT}.new", run_dir / f"{CHECKPOINT}.old"


def checkpoint_path(run_dir: str | Path) -> Path | None:
    """The checkpoint directory a resume reads: ``checkpoint/``, or ``checkpoint.old/`` if
    a kill came between the two renames of a commit; None without one."""
    final, _, old = _aside(Path(run_dir))
    return final if final.exists() else old if old.exists() else None


def save_checkpoint(run_dir: str | Path, files: dict[str, bytes], step: int) -> None:
    """Commit ``files`` as the checkpoint of ``step``: all of them or none (see the module
    docstring). Only the run's single writer calls this."""
    run_dir = Path(run_dir)
    final, new, old = _aside(run_dir)
    if new.exists():
        shutil.rmtree(new)  # a commit killed before its renames
    new.mkdir()
    entries = {}
    for name, data in files.items():
        _write_synced(new / name, data)
        entries[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
    manifest = {"format": CHECKPOINT_FORMAT, "step": step, "files": entries}
    _write_synced(new / "manifest.json", json_text(manifest).encode())  # last: it vouches for the rest
    fsync_directory(new)
    fault("checkpoint-written")
    if final.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(final, old)
        fault("checkpoint-aside")
    os.replace(new, final)
    fsync_directory(run_dir)
    fault("checkpoint-committed")
    if old.exists():
        shutil.rmtree(old)


def damaged(ckpt: Path, problem: str) -> ConfigError:
    return ConfigError(f"the checkpoint {ckpt} is damaged: {problem}; delete {ckpt} to restart the run from step 0")


def load_checkpoint(run_dir: str | Path) -> tuple[Path, dict[str, bytes], bool] | None:
    """The checkpoint's directory, its files' bytes and whether it is verified (False: an
    older physgrad's checkpoint without a manifest, loaded as it is); None without one.

    Every file is checked against ``manifest.json`` (present, size, sha256, the step in
    ``counters.json``); anything wrong is a one-line ConfigError."""
    ckpt = checkpoint_path(run_dir)
    if ckpt is None:
        return None
    try:
        names = {p.name for p in ckpt.iterdir()}
        if "manifest.json" not in names:
            if "counters.json" not in names:
                raise damaged(ckpt, "it has neither manifest.json nor counters.json (an interrupted write?)")
            if "state.eqx" not in names:
                raise damaged(ckpt, "state.eqx is missing")
            return ckpt, {n: (ckpt / n).read_bytes() for n in ("state.eqx", "counters.json")}, False
        try:
            manifest = json.loads((ckpt / "manifest.json").read_text())
            version, step, entries = manifest["format"], manifest["step"], manifest["files"]
            listed = {name: (int(e["bytes"]), str(e["sha256"])) for name, e in entries.items()}
        except (ValueError, KeyError, TypeError, AttributeError):
            raise damaged(ckpt, "manifest.json is not a valid manifest") from None
        if not isinstance(version, int) or version > CHECKPOINT_FORMAT:
            raise ConfigError(f"the checkpoint {ckpt} has format {version!r}, newer than this physgrad reads "
                              f"({CHECKPOINT_FORMAT}); resume with the physgrad that wrote it")  # fmt: skip
        files = {}
        for name in ("state.eqx", "counters.json"):
            if name not in listed:
                raise damaged(ckpt, f"manifest.json does not list {name}")
            if name not in names:
                raise damaged(ckpt, f"{name} is missing")
            data = (ckpt / name).read_bytes()
            size, digest = listed[name]
            if len(data) != size:
                raise damaged(
                    ckpt, f"{name} has {len(data)} bytes, the manifest says {size} (truncated or overwritten)"
                )
            if hashlib.sha256(data).hexdigest() != digest:
                raise damaged(ckpt, f"{name} does not match its checksum (changed bytes)")
            files[name] = data
    except OSError as e:
        raise damaged(ckpt, f"cannot read it ({e.strerror or e})") from None
    counters = parse_counters(ckpt, files["counters.json"])
    if counters.get("step") != step:
        raise damaged(ckpt, f"counters.json is at step {counters.get('step')}, the manifest at step {step}")
    return ckpt, files, True


def parse_counters(ckpt: Path, data: bytes) -> dict[str, Any]:
    """``counters.json`` as a dict, or a one-line ConfigError."""
    try:
        counters = json.loads(data.decode())
    except (ValueError, UnicodeDecodeError):
        raise damaged(ckpt, "counters.json is not valid JSON") from None
    if not isinstance(counters, dict):
        raise damaged(ckpt, "counters.json is not a JSON object")
    return counters


# --- the test-only fault hook --------------------------------------------------------------------
_passed: dict[str, int] = {}  # times each point was passed in this process (test hook only)


def fault(point: str) -> None:
    """Kill or pause the process at ``point`` if ``$PHYSGRAD_TEST_FAULT`` asks for it
    (test-only; see the module docstring). Reads the variable each time: importing this
    module changes nothing."""
    spec = os.environ.get(FAULT_VARIABLE)
    if not spec:
        return
    for item in spec.split(","):
        name, _, action = item.strip().partition(":")
        if name != point:
            continue
        _passed[point] = count = _passed.get(point, 0) + 1
        action, _, at = action.partition("@")
        if at and count != int(at):
            continue
        if action == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        elif action.startswith("sleep:"):
            time.sleep(float(action.split(":", 1)[1]))
        elif action == "term":
            os.kill(os.getpid(), signal.SIGTERM)
        elif action == "int":
            os.kill(os.getpid(), signal.SIGINT)
