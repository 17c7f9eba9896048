"""A run directory as one unit: written aside, swapped in whole, checked before reading.

`simulate` writes every file of a run into a temporary sibling directory
(`.NAME.partial-PID-XXXX` beside `NAME`) and, once all are written, records them
in `manifest.json` (run id, seed, scene, size and SHA-256 of each file) and swaps
the directory in under an exclusive lock on the parent directory: the previous
run (if any) is renamed aside and deleted, the new one renamed into place, with
SIGINT/SIGTERM held back for those two renames. Hence

- re-running into a directory leaves no stale file of the old run;
- an interrupted run (an exception, KeyboardInterrupt) leaves the old run intact
  and no temporary directory (a killed one leaves `.NAME.partial-PID-*`, removed
  by the next run into NAME once PID is gone);
- two runs into one directory never mix: the last to finish wins, whole.

An existing directory is replaced only when it is empty or holds a run
(`manifest.json`, or `summary.json` and `bands` from before manifests): never a directory
of other files. `plot` and `analyze` call `check_run` first: a directory
without a manifest, with a file missing, changed or foreign, is refused.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import uuid
from pathlib import Path
from typing import Iterator

from .errors import ConfigError

MANIFEST = "manifest.json"
FORMAT = "clumpylen-run/1"
# written into a finished run after the manifest: not checked
_UNLISTED_DIRS = ("plots",)
# what `plot` and `analyze` read: every such file must be in the manifest
_READ_PATTERNS = ("bands/*.fits", "catalog.ecsv", "summary.json")


@dataclasses.dataclass
class RunDirectory:
    """The temporary directory a run writes into (`path`) and what its manifest records."""

    path: Path
    final: Path
    meta: dict


def _is_run(d: Path) -> bool:
    """A run of ours: a manifest, or (runs from before manifests) summary.json and bands."""
    return (d / MANIFEST).is_file() or ((d / "summary.json").is_file() and (d / "bands").exists())


def check_target(out_dir, setting: str = "--out") -> Path:
    """The absolute output path, or ConfigError when a run may not be written there.

    Allowed: a new path (parents are created), an empty directory, or a previous run.
    """
    text = os.fspath(out_dir)
    if not text.strip():
        raise ConfigError(setting, text, "a directory path (not empty)")
    out = Path(os.path.realpath(os.path.expanduser(text)))
    if out.exists() and not out.is_dir():
        raise ConfigError(setting, text, "a directory (this path is a file)")
    if out.is_dir():
        try:
            entries = os.listdir(out)
        except OSError as exc:
            raise ConfigError(setting, text, f"a readable directory ({exc.strerror})") from exc
        if entries and not _is_run(out):
            raise ConfigError(setting, text, "a new path, an empty directory or a previous run's "
                              "directory (this one holds other files: "
                              + ", ".join(sorted(entries)[:3]) + (", ..." if len(entries) > 3 else "")
                              + "; a run replaces its directory whole)")
    for parent in out.parents:   # the nearest existing parent must be a directory
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(setting, text, f"a path under a directory ({parent} is a file)")
            break
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove_stale(parent: Path, name: str) -> None:
    """Temporary directories of killed runs into `name` (their process is gone)."""
    for kind in ("partial", "old"):
        for d in parent.glob(f".{name}.{kind}-*"):
            try:
                pid = int(d.name[len(name) + len(kind) + 3:].split("-")[0])
            except ValueError:
                continue
            if pid != os.getpid() and not _pid_alive(pid):
                shutil.rmtree(d, ignore_errors=True)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _entry(path: Path) -> dict:
    return {"size": path.stat().st_size, "sha256": _sha256(path)}


def _listed_files(root: Path) -> list[str]:
    out = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and rel != MANIFEST and rel.split("/")[0] not in _UNLISTED_DIRS:
            out.append(rel)
    return out


def write_manifest(root, meta: dict | None = None) -> dict:
    """Record every file under `root` (but plots/) in root/manifest.json; returns the manifest."""
    from .io import write_json

    root = Path(root)
    manifest = {"format": FORMAT, "run_id": uuid.uuid4().hex, **(meta or {}),
                "files": {rel: _entry(root / rel) for rel in _listed_files(root)}}
    write_json(root / MANIFEST, manifest)
    return manifest


def update_manifest(root, *relpaths: str) -> None:
    """Re-record files a command rewrote in a finished run (e.g. `analyze` → summary.json)."""
    from .io import write_json

    root = Path(root)
    path = root / MANIFEST
    if not path.is_file():
        return
    manifest = json.loads(path.read_text(encoding="utf-8"))
    for rel in relpaths:
        manifest["files"][rel] = _entry(root / rel)
    write_json(path, manifest)


def check_run(run_dir, setting: str = "run directory") -> dict:
    """The manifest of a complete run, or ConfigError naming what is wrong with it."""
    root = Path(run_dir)
    text = os.fspath(run_dir)
    if not root.is_dir():
        raise ConfigError(setting, text, "an existing directory written by `clumpylen simulate` "
                          "(run directory not found)")
    path = root / MANIFEST
    if not path.is_file():
        raise ConfigError(setting, text, f"a complete run ({MANIFEST} missing: the run was "
                          "interrupted, is not a clumpylen run, or predates manifests; rerun simulate)")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        files = manifest["files"]
        ok = manifest.get("format") == FORMAT and isinstance(files, dict)
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{text}/{MANIFEST}", "<unreadable>", f"a run manifest (JSON): {exc}") from exc
    if not ok:
        raise ConfigError(f"{text}/{MANIFEST}", manifest.get("format"), f"a manifest of format {FORMAT}")
    for rel, entry in files.items():
        p = root / rel
        if not p.is_file():
            raise ConfigError(setting, text, f"a complete run ({rel} is missing)")
        if p.stat().st_size != entry.get("size") or _sha256(p) != entry.get("sha256"):
            raise ConfigError(setting, text, f"an unmodified run ({rel} changed since the run "
                              f"{manifest.get('run_id')} wrote it)")
    for pattern in _READ_PATTERNS:
        for p in root.glob(pattern):
            rel = p.relative_to(root).as_posix()
            if rel not in files:
                raise ConfigError(setting, text, f"files of one run ({rel} is not part of run "
                                  f"{manifest.get('run_id')})")
    return manifest


def _act_as(handler, signum, frame=None):
    """Do what `handler` (a signal's handler before ours) does with signum: call it (e.g.
    KeyboardInterrupt from the default SIGINT handler), or for SIG_DFL put it back and raise
    the signal again; SIG_IGN: nothing."""
    if callable(handler):
        handler(signum, frame)
    elif handler == signal.SIG_DFL:
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)


@contextlib.contextmanager
def _signals_held():
    """Hold SIGINT/SIGTERM back (acted on when the block ends), so that no interrupt splits
    what the block does. Python-level handlers, not a signal mask: XLA's threads would take
    a masked signal (possible in the main thread only; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    old = {s: signal.signal(s, lambda signum, frame: received.append(signum))
           for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        for s in received[:1]:
            _act_as(old[s], s)


@contextlib.contextmanager
def _signals_noted(received: list):
    """SIGINT/SIGTERM handled as before (KeyboardInterrupt, ...), and noted in `received`:
    Python swallows an exception raised where it cannot propagate (seen: a SIGINT landing in
    JAX's gc callback printed "Exception ignored" and the run went on to replace the old
    one), so `run_directory` checks the note before it swaps the run in. Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {}

    def note(signum, frame):
        received.append(signum)
        _act_as(old[signum], signum, frame)

    # an ignored signal (SIGINT of a job started with & from a script) stays ignored
    old.update({s: signal.signal(s, note) for s in (signal.SIGINT, signal.SIGTERM)
                if signal.getsignal(s) not in (signal.SIG_IGN, None)})
    old_hook = sys.unraisablehook

    def unraisable(info):
        # the swallowed KeyboardInterrupt is noted above and acted on after the block: not
        # printed as "Exception ignored ... Traceback" on the user's terminal
        if not (received and info.exc_type is not None
                and issubclass(info.exc_type, KeyboardInterrupt)):
            old_hook(info)

    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        sys.unraisablehook = old_hook
        for s, handler in old.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def _locked(directory: Path):
    """An exclusive flock on a directory (released when the block ends; leaves no file)."""
    import fcntl

    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)   # closing releases the lock


def _swap_in(tmp: Path, out: Path, setting: str) -> None:
    with _locked(out.parent), _signals_held():
        check_target(out, setting)   # again: another process may have written there meanwhile
        old = None
        if out.exists():
            old = out.parent / f".{out.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
            os.rename(out, old)
        try:
            os.rename(tmp, out)
        except BaseException:
            if old is not None:
                os.rename(old, out)
            raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def run_directory(out_dir, *, setting: str = "--out") -> Iterator[RunDirectory]:
    """Write a run aside and swap it into `out_dir` when the block ends without error.

    Yields a RunDirectory: write into `.path`; put the run's seed, scene name etc. in
    `.meta` (they go into the manifest). On any exception (KeyboardInterrupt too) the
    temporary directory is removed and `out_dir` is left as it was.
    """
    out = check_target(out_dir, setting)
    parent = out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError as exc:
        raise ConfigError(setting, os.fspath(out_dir), f"a path under a directory ({exc.filename} "
                          "is a file)") from exc
    _remove_stale(parent, out.name)
    tmp = None
    try:
        with _signals_held():   # a SIGINT waits until tmp is known, then is handled below
            tmp = Path(tempfile.mkdtemp(dir=parent, prefix=f".{out.name}.partial-{os.getpid()}-"))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)   # mkdtemp makes it private (0700)
        run = RunDirectory(tmp, out, {})
        received = []
        with _signals_noted(received):
            yield run
        if received:     # an interrupt whose exception was swallowed on the way
            raise KeyboardInterrupt
        write_manifest(tmp, run.meta)
        _swap_in(tmp, out, setting)
    except BaseException as exc:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
            if isinstance(exc, OSError) and str(exc.filename or "").startswith(str(tmp)):
                # name the file the user asked for, not its temporary twin
                final = str(out) + str(exc.filename)[len(str(tmp)):]
                raise type(exc)(exc.errno, exc.strerror, final) from exc
        raise


def describe_oserror(exc: OSError) -> str:
    """One line for an OSError: what failed and on which path."""
    what = exc.strerror or (errno.errorcode.get(exc.errno, "") if exc.errno else "") or str(exc)
    paths = [p for p in (exc.filename, exc.filename2) if p]
    return f"{what}: {' -> '.join(map(os.fspath, paths))}" if paths else what
