"""Atomic output: write to a temporary path beside the target, then rename.

A reader never sees a half-written file, and an interrupted run leaves either
the old file or the new one, never a fragment. What may be written where is
:mod:`cpas_bayes.core.ownership`'s rule: a file or folder is created new or
replaces only one cpas-bayes wrote, and every name written is recorded in its
folder's marker. A failed write (no permission, disk full, a name too long)
ends as an :class:`~cpas_bayes.core.ownership.OutputError` naming the path and
the fix, with no temporary file left; a process ending on a signal removes its
temporary files with :func:`remove_temporaries`.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import secrets
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from cpas_bayes.core.ownership import (ADOPTED, CREATED, MARKER, OLD_SUFFIX, TEMP_SUFFIX, OutputError, claim_folder,
                                       ensure_folder, fcntl, foreign_entry, new_marker, output_error, read_marker, record,
                                       refuse_foreign, rewrite_marker, seal, umask)

_TEMPORARIES = set()  # temporary files and folders of the writes under way in this process


def remove_temporaries():
    """Delete the temporary files and folders of the writes under way (for a process ending on a signal)."""
    for path in list(_TEMPORARIES):
        _TEMPORARIES.discard(path)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                path.unlink()


def _temp_prefix(name):
    return f".{name[:100]}."


@contextlib.contextmanager
def atomic_path(target):
    """Yield a temporary path in the target's folder; rename it onto ``target`` on success.

    ``target`` is new or a file cpas-bayes wrote (listed in its folder's
    marker); anyone else's file is refused and left as it is.
    """
    target = Path(target)
    folder = target.parent
    try:
        marker = ensure_folder(folder)
        if os.path.lexists(target):
            if target.is_dir() and not target.is_symlink():
                raise IsADirectoryError(errno.EISDIR, "is a folder", str(target))
            if marker is None or target.name not in marker.entries:
                raise OutputError(target, "", "exists and was not written by cpas-bayes, so it is not replaced",
                                  "move it away, or give a new or empty output folder")
        elif marker is not None:
            record(folder, target.name)  # the name first, then the file
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(target.name), suffix=TEMP_SUFFIX, dir=folder)
        os.close(fd)
    except OSError as exc:
        raise output_error(exc, target) from None
    tmp = Path(tmp)
    _TEMPORARIES.add(tmp)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give it the mode a plain open() would.
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, target)
    except OSError as exc:
        raise output_error(exc, target) from None
    finally:
        _TEMPORARIES.discard(tmp)
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()

def write_text(target, text):
    """Write ``text`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def jsonable(value):
    """Plain Python values (DataFrames as lists of records), NaN/inf → None, for ``write_json``."""
    import pandas as pd

    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, pd.DataFrame):
        return [jsonable(r) for r in value.to_dict(orient="records")]
    if isinstance(value, np.ndarray):
        return [jsonable(v) for v in value.tolist()]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_json(target, obj):
    """Write ``obj`` as indented JSON atomically (numpy scalars and arrays allowed)."""
    write_text(target, json.dumps(obj, indent=2, default=_json_default, allow_nan=False) + "\n")


def write_csv(target, frame, **kwargs):
    """Write a DataFrame as CSV atomically."""
    with atomic_path(target) as tmp:
        frame.to_csv(tmp, index=False, **kwargs)


def _check_replaceable(target):
    """Refuse a folder ``target`` that the package may not replace (it is new, empty or the package's)."""
    if not os.path.lexists(target):
        return
    if target.is_symlink() or not target.is_dir():
        raise OutputError(target, "", "exists and is not a folder cpas-bayes wrote, so it is not replaced",
                          "move it away, or give a new or empty output folder")
    marker = read_marker(target)
    found = foreign_entry(target, recursive=marker is not None)
    if found is not None:
        raise refuse_foreign(target, found)


def _install(tmp, target):
    """Put the finished folder ``tmp`` in place of ``target``."""
    if not os.path.lexists(target):
        os.rename(tmp, target)
        return
    _check_replaceable(target)  # again, just before touching it
    marker = read_marker(target)
    if marker is not None and marker.created:  # the package's own folder: replaced whole, by two renames
        old = target.with_name(f"{_temp_prefix(target.name)}{secrets.token_hex(4)}{OLD_SUFFIX}")
        os.rename(target, old)
        try:
            os.rename(tmp, target)
        except BaseException:
            os.rename(old, target)
            raise
        shutil.rmtree(old, ignore_errors=True)
        return
    # a folder the package was given empty: it keeps its identity (owner, mode); its contents change
    for name in marker.entries if marker is not None else ():
        path = target / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif os.path.lexists(path):
            path.unlink()
    names = [n for n in os.listdir(tmp) if n != MARKER]
    rewrite_marker(target, ADOPTED, names)
    for name in names:
        os.rename(tmp / name, target / name)


@contextlib.contextmanager
def atomic_directory(target):
    """Yield a new temporary folder beside ``target``; on success it becomes ``target``.

    ``target`` may be new, empty, or a folder holding only what cpas-bayes
    wrote (refused otherwise, before the work starts). A folder the package
    created is replaced whole; an empty folder it was given keeps its
    identity and receives the new contents. Errors of the work itself pass
    through unchanged.
    """
    target = Path(target)
    parent = target.parent
    tmp = None
    try:
        parent_marker = ensure_folder(parent)
        _check_replaceable(target)
        tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(target.name), suffix=TEMP_SUFFIX, dir=parent))
        _TEMPORARIES.add(tmp)
        os.chmod(tmp, 0o777 & ~umask())  # mkdtemp makes it private (0700); a created folder gets the usual mode
        new_marker(tmp, CREATED)
    except OSError as exc:
        if tmp is not None:
            _TEMPORARIES.discard(tmp)
            shutil.rmtree(tmp, ignore_errors=True)
        raise output_error(exc, target) from None
    try:
        yield tmp
        try:
            seal(tmp)  # everything in the fresh folder is the package's
            if parent_marker is not None:
                record(parent, target.name)
            _install(tmp, target)
        except OSError as exc:
            raise output_error(exc, target) from None
    finally:
        _TEMPORARIES.discard(tmp)
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


@contextlib.contextmanager
def exclusive_writer(target, wait=30.0):
    """Be the only process writing ``target``, by holding the lock file ``.NAME.lock`` beside it.

    The folder is claimed as an output folder (:func:`~cpas_bayes.core.ownership.claim_folder`).
    The lock is the kernel's (``flock``): it goes with the process that holds
    it, so a killed writer's lock is free at once, whatever the file says; the
    file holds the holder's pid for the message. A lock held by a live process
    is waited for up to ``wait`` seconds (a killed run's workers take a moment
    to end), then refused.
    """
    if target is None:  # nothing to guard
        yield None
        return
    target = Path(target)
    lock = target.with_name(f".{target.name}.lock")
    claim_folder(lock.parent)
    try:
        marker = read_marker(lock.parent)
        if marker is not None and lock.name not in marker.entries:
            if os.path.lexists(lock):
                raise refuse_foreign(lock.parent, lock)
            record(lock.parent, lock.name)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as exc:
        raise output_error(exc, lock) from None
    try:
        if fcntl is not None:
            deadline = time.monotonic() + wait
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
                        raise OutputError(target, "", f"is being written by another running process (pid {holder}); "
                                                      "two writers would mix their results",
                                          f"let that run finish, or stop it (kill {holder}), then rerun") from None
                    time.sleep(0.2)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        yield lock
    finally:
        os.close(fd)  # releases the lock
