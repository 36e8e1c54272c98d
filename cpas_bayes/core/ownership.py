"""Output folders: where a command may write, and what it may replace there.

**The rule.** A command writes only inside its ``--out`` folder, and it
deletes, renames or replaces only what cpas-bayes wrote. An ``--out`` folder is
usable when it does not exist yet, is empty, or holds only what cpas-bayes
wrote there; anything else (an existing file, a folder holding a file of the
user's, a path through a file, a name the file system cannot hold, a folder
that cannot be written) is refused before any work starts, naming the path
and the fix, and nothing is touched.

**How it is known what cpas-bayes wrote.** Every folder the package writes
into holds a small marker file, :data:`MARKER`, whose first lines say that it
is a cpas-bayes output folder and whether the package created the folder
itself (``created``) or was given it empty (``adopted``); then one line per
entry (file or sub-folder) the package put there, as a JSON string. A name is
recorded *before* its file is created (a kill leaves at most a name without
a file, never a file without its name); lines are appended with ``O_APPEND``,
so worker processes writing side by side into one folder need no lock. A
folder whose marker lists every entry in it (and so on down) is the package's;
the temporary files of an interrupted write (``.NAME.….cpas-tmp``,
``.NAME.….cpas-old``) count as the package's too.

:func:`check_output` is the up-front check a command runs on ``--out`` (and
:func:`check_outside_inputs`: never inside an input bundle folder);
:func:`claim_folder` makes (or adopts) an output folder and is called by every
writer that takes a folder; :mod:`cpas_bayes.core.files` creates, replaces and
records single files and whole folders under this rule.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
from pathlib import Path

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.inputs import broken_link

try:  # POSIX; without it, folders are created without the creator's lock
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

MARKER = ".cpas-bayes"
_HEADER = "cpas-bayes output folder: the names below were written here by cpas-bayes (one JSON string a line)"
CREATED, ADOPTED = "created", "adopted"
TEMP_SUFFIX, OLD_SUFFIX = ".cpas-tmp", ".cpas-old"
NAME_MAX = 255


class OutputError(InputError):
    """An output the package refuses to write (or could not write), with the path and the fix."""


FOREIGN_FIX = ("move it out of the folder, or give a new or empty --out folder (cpas-bayes writes only into folders "
               "it created, and replaces only what it wrote)")


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file or folder of the package (left by an interrupted write)."""
    return name.startswith(".") and name.endswith((TEMP_SUFFIX, OLD_SUFFIX))


def umask() -> int:
    """This process' umask, read without changing it where the system allows (Linux)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# ---------------------------------------------------------------------------
# the marker


class Marker:
    """What a folder's marker says: created or adopted, and the names the package wrote there."""

    def __init__(self, status, entries):
        self.status, self.entries = status, entries

    @property
    def created(self):
        return self.status == CREATED


def read_marker(folder) -> Marker | None:
    """The marker of ``folder``, or None where the package never wrote (no marker file)."""
    try:
        raw = (Path(folder) / MARKER).read_text(encoding="utf-8")
    except (FileNotFoundError, NotADirectoryError):
        return None
    except UnicodeDecodeError:
        return Marker(ADOPTED, set())
    lines = raw.split("\n")
    entries = set()
    for line in lines[2:]:
        try:
            name = json.loads(line)
        except ValueError:  # an empty last line, or a line a kill cut short
            continue
        if isinstance(name, str):
            entries.add(name)
    return Marker(lines[1].strip() if len(lines) > 1 else ADOPTED, entries)


def _marker_text(status, names=()):
    return "".join(f"{line}\n" for line in (_HEADER, status, *(json.dumps(n) for n in sorted(names))))


def new_marker(folder, status):
    """Write the marker of a folder that has none (a no-op if another process just wrote one).

    The marker appears whole: it is written under a temporary name and
    hard-linked into place (a link, unlike a rename, fails if the marker
    exists). Created empty and then filled, it could be read empty, have a
    name appended by another process, and lose that name under the header.
    """
    folder = Path(folder)
    path = folder / MARKER
    tmp = folder / f".{MARKER}.{os.getpid()}.{secrets.token_hex(4)}{TEMP_SUFFIX}"
    tmp.write_text(_marker_text(status), encoding="utf-8")
    try:
        os.link(tmp, path)
    except FileExistsError:
        pass
    except OSError as exc:  # a file system without hard links: create exclusively, then fill
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
            raise
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            return
        try:
            os.write(fd, _marker_text(status).encode("utf-8"))
        finally:
            os.close(fd)
    finally:
        tmp.unlink(missing_ok=True)


def rewrite_marker(folder, status, names):
    """Replace a folder's marker (status and the full list of names) in one rename."""
    folder = Path(folder)
    tmp = folder / f".{MARKER}.{os.getpid()}{TEMP_SUFFIX}"
    tmp.write_text(_marker_text(status, names), encoding="utf-8")
    os.replace(tmp, folder / MARKER)


def record(folder, *names):
    """Add ``names`` to the marker of ``folder`` (one appended write; several processes may append)."""
    if not names:
        return
    text = "".join(json.dumps(n) + "\n" for n in names).encode("utf-8")
    fd = os.open(Path(folder) / MARKER, os.O_WRONLY | os.O_APPEND)
    try:
        os.write(fd, text)
    finally:
        os.close(fd)


def seal(folder):
    """Record everything in a folder the package has just made (a temporary folder) as the package's."""
    folder = Path(folder)
    marker = read_marker(folder)
    if marker is None:
        new_marker(folder, CREATED)
    names = sorted(n for n in os.listdir(folder) if n != MARKER and not is_temporary(n))
    record(folder, *[n for n in names if marker is None or n not in marker.entries])
    for name in names:
        path = folder / name
        if path.is_dir() and not path.is_symlink():
            seal(path)


@contextlib.contextmanager
def _folder_lock(folder):
    """Hold an exclusive lock on ``folder`` (best effort: none where it cannot be opened)."""
    fd = None
    if fcntl is not None:
        try:
            fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            if fd is not None:
                os.close(fd)
            fd = None
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)  # releases the lock


# ---------------------------------------------------------------------------
# what belongs to the package


def foreign_entry(folder, recursive=True) -> Path | None:
    """The first entry of ``folder`` (and, if ``recursive``, of its sub-folders) cpas-bayes did not write."""
    folder = Path(folder)
    marker = read_marker(folder)
    with os.scandir(folder) as it:
        entries = sorted(it, key=lambda e: e.name)
    for e in entries:
        if e.name == MARKER or is_temporary(e.name):
            continue
        if marker is None or e.name not in marker.entries or e.is_symlink():
            return Path(e.path)  # the package never makes symbolic links
        if recursive and e.is_dir(follow_symlinks=False):
            inner = foreign_entry(e.path)
            if inner is not None:
                return inner
    return None


def refuse_foreign(path, found, what="folder"):
    """The error for a folder holding ``found``, which cpas-bayes did not write."""
    return OutputError(found, "", f"was not written by cpas-bayes, so the {what} {path} is not used "
                                  "(nothing in it was changed)", FOREIGN_FIX)


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            return candidate
    return Path(path.anchor or ".")


def _name_max(folder):
    try:
        return os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        return NAME_MAX


def check_output(path, option="--out") -> Path:
    """Refuse an output folder a command may not use, before any work; create nothing.

    Usable: a folder that does not exist (under folders, writable), an empty
    folder, or a folder holding only what cpas-bayes wrote there.
    """
    path = Path(path)
    fix_other = f"give another {option} folder"
    anchor = _nearest_existing(path.absolute())
    name_max = _name_max(anchor if anchor.is_dir() else anchor.parent)
    for part in path.parts:
        if len(os.fsencode(part)) > name_max:
            raise OutputError(path, "", f"the name '{part[:40]}…' has {len(os.fsencode(part))} bytes; the file "
                                        f"system allows {name_max}", f"use shorter names, or {fix_other}")
    if os.path.lexists(path):
        if broken_link(path):
            raise OutputError(path, "", "is a link to nothing (a broken symbolic link, or a loop of links); "
                                        "the link was left as it is", f"{fix_other}, or remove the link")
        if not path.is_dir():
            raise OutputError(path, "", f"exists and is a file, not a folder ({option} must be a folder; the file "
                                        "was left as it is)", f"{fix_other} (new, empty, or written by cpas-bayes)")
        try:
            found = foreign_entry(path)
        except OSError as exc:
            raise output_error(exc, path) from None
        if found is not None:
            raise refuse_foreign(path, found, f"{option} folder")
        where = path
    else:
        if not anchor.is_dir():
            raise OutputError(path, "", f"{anchor} is a file, so no folder can be made under it",
                              f"{fix_other}, whose parent folders are folders")
        where = anchor
    if not os.access(where, os.W_OK | os.X_OK):
        which = "the folder" if where == path else f"{where}, where it would be made,"
        raise OutputError(path, "", f"{which} cannot be written (permission denied)",
                          f"{fix_other} that you can write to, or change the permissions")
    return path


def check_outside_inputs(path, inputs, option="--out", what="bundle folder") -> Path:
    """Refuse an output folder ``path`` that is, or lies inside, one of the input folders ``inputs``, before
    any work; symbolic links resolved on both sides (a link to a bundle is that bundle).

    A bundle folder is its test.toml, its data.csv and the files a user keeps with them: outputs written
    into it would be taken for part of the bundle when it is copied, archived or read as an input again.
    """
    out = Path(path).resolve()
    for folder in inputs:
        resolved = Path(folder).resolve()
        if out == resolved or out.is_relative_to(resolved):
            inside = out != resolved
            beside = resolved.parent / f"{resolved.name}-{out.name if inside else 'out'}"
            raise OutputError(path, "", f"{option} {'lies inside' if inside else 'is'} the {what} {folder}: "
                              "the outputs would be written among the bundle's own files",
                              f"give {option} a folder outside {folder}, e.g. {beside}")
    return Path(path)


def claim_folder(path) -> Path:
    """Make ``path`` an output folder of the package: create it (with its marker) or adopt it if empty.

    A folder that already has a marker is taken as it is (what may be
    replaced in it is decided file by file); an existing folder without a
    marker holding anything is refused, naming the first entry.
    """
    path = Path(path)
    try:
        marker = ensure_folder(path)
        if marker is None:
            with _folder_lock(path):
                if read_marker(path) is None:
                    found = foreign_entry(path, recursive=False)
                    if found is not None:
                        raise refuse_foreign(path, found)
                    new_marker(path, ADOPTED)
    except OSError as exc:
        raise output_error(exc, path) from None
    return path


def ensure_folder(path) -> Marker | None:
    """Make sure folder ``path`` exists; return its marker (None for a folder the package did not make).

    Missing folders are created one by one, each with its marker (``created``)
    and its name recorded in its parent's marker when the parent has one; a
    path through a file raises ``NotADirectoryError``.
    """
    path = Path(path)
    # is_dir() after lexists(): another process (a fit's other ensemble) may make the folder in between
    if os.path.lexists(path) and not path.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "a file is in the way of a folder", str(path))
    if path.is_dir():
        marker = read_marker(path)
        if marker is None and path.parent != path:
            # a folder being created by another process has no marker for an instant: wait for its creator
            with _folder_lock(path.parent):
                marker = read_marker(path)
        return marker
    parent_marker = ensure_folder(path.parent)
    with _folder_lock(path.parent):
        if parent_marker is not None:
            record(path.parent, path.name)  # the name first, then the folder
        try:
            os.mkdir(path)  # mode 0o777 less the umask, as a plain mkdir gives
        except FileExistsError:
            if not path.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, "a file is in the way of a folder", str(path)) from None
            marker = read_marker(path)
            if marker is not None:  # made by another process of ours just before we held the lock
                return marker
        new_marker(path, CREATED)
    return read_marker(path)


def output_error(exc: OSError, path, verb="written") -> OutputError:
    """An :class:`OutputError` saying in words why ``path`` could not be ``verb``, and what to do."""
    where = exc.filename or path
    code = exc.errno
    if code in (errno.EACCES, errno.EPERM):
        problem = f"cannot be {verb} (permission denied)"
        fix = ("give an output folder you can write to, or change its permissions" if verb == "written" else
               "check that path's permissions (for an output: give a folder you can write to)")
    elif code == errno.EROFS:
        problem, fix = "is on a read-only file system", "give an output folder on a writable disk"
    elif code in (errno.ENOSPC, getattr(errno, "EDQUOT", -1), errno.EFBIG):
        problem, fix = f"cannot be {verb}: no space left (disk full or quota reached)", \
            "free some space or give an output folder on another disk, then rerun (nothing half-written was kept)"
    elif code == errno.ENAMETOOLONG:
        problem, fix = "has a name too long for the file system", "use shorter folder and file names"
    elif code == errno.ENOTDIR:
        problem, fix = "cannot be made: a file is in the way where a folder should be", \
            "give an output path whose parent folders are folders"
    elif code == errno.EISDIR:
        problem, fix = "is a folder where a file should be", "move that folder away or give another path"
    elif code == errno.EEXIST:
        problem, fix = "already exists and was not written by cpas-bayes", FOREIGN_FIX
    elif code == errno.ENOENT:
        problem, fix = "does not exist", "check the path"
    else:
        problem, fix = f"cannot be {verb} ({exc.strerror or exc})", "check the path and the disk, then rerun"
    return OutputError(where, "", problem, fix)
