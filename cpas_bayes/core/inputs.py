"""Reading what users hand us, within stated limits: TOML documents and names.

Every file the package reads as configuration (bundle ``test.toml``, prior
files, campaign configs, memos) goes through :func:`read_toml`, and every name
that can become part of a path (test names, parachute ids, kinds, configuration
names) through :func:`check_name`. A refusal is an :class:`InputError` naming
the file, the key and the fix, raised before any work starts.

Limits (stated in the README's reliability section):

* a TOML file is at most ``MAX_TOML_BYTES``; UTF-8, with or without a byte-order mark;
* tables and arrays nest at most ``MAX_TOML_DEPTH`` deep;
* integers fit in 64 bits (the TOML specification's own range; ``tomllib``
  does not enforce it, and a 400-digit integer would overflow later as a float);
* a string value is at most ``MAX_STRING`` characters;
* a name is 1–``MAX_NAME`` printable characters, no path separator, no
  leading dot or surrounding space: one path component that cannot climb out
  of the folder it is placed in;
* free text that is printed (labels, phases, column names) is one line of
  printable characters (no newline, no terminal escape), at most ``MAX_TEXT``;
* a key that is not one of the format's keys is refused with the nearest valid
  name (:func:`check_keys`): a misspelt ``weight_sigm`` is an error, not a
  silently ignored line.

Text from a file that is shown in a message goes through :func:`shown`, so a
refusal cannot carry a terminal escape or a megabyte of text to a user.

Result files the package wrote itself and reads back (``summary.json`` of a
fit, ``map.json``) go through :func:`read_json`: at most ``MAX_JSON_BYTES``,
UTF-8, valid JSON (``NaN``/``Infinity`` refused), nested at most
``MAX_JSON_DEPTH`` deep, and an object at the top; its ``fix`` says what to
re-run. :func:`nearest` finds the valid name a misspelt key most likely meant,
:func:`did_you_mean` says it in a message.
"""

from __future__ import annotations

import difflib
import json
import os
import sys
import tomllib
from pathlib import Path

from cpas_bayes.core.errors import InputError

MAX_TOML_BYTES = 5_000_000
MAX_TOML_DEPTH = 16
MAX_STRING = 10_000
MAX_NAME = 64
MAX_TEXT = 128
_INT_LIMIT = 2**63
MAX_JSON_BYTES = 50_000_000
MAX_JSON_DEPTH = 64


def broken_link(path):
    """Whether ``path`` is a symbolic link to nothing: its target missing, or a loop of links."""
    path = Path(path)
    return path.is_symlink() and not path.exists()


def not_a_file(path):
    """Why an existing ``path`` is not a regular file to read (a broken link or loop of links, a folder, a pipe
    or device), or None if it is one or is not there at all."""
    path = Path(path)
    if not os.path.lexists(path) or path.is_file():
        return None
    if broken_link(path):
        return "is a link to nothing (a broken symbolic link, or a loop of links)"
    if path.is_dir():
        return "is a folder, not a file"
    return "not a regular file (a pipe, a socket or a device)"


def read_toml(path, error=InputError, fix_syntax="correct the TOML syntax at that line",
              fix_file="give the path of the .toml file itself"):
    """The document of TOML file ``path``, checked against the limits above.

    ``error`` is the :class:`InputError` subclass to raise (e.g. ``BundleError``); ``fix_file`` the fix when
    ``path`` is there but not a file (a folder, a broken link, a pipe).
    """
    path = Path(path)
    problem = not_a_file(path)
    if problem:
        raise error(path, "", problem, fix_file)
    if not path.is_file():
        raise error(path, "", "file not found", "check the path")
    size = path.stat().st_size
    if size > MAX_TOML_BYTES:
        raise error(path, "", f"{size:,} bytes, more than the {MAX_TOML_BYTES:,} a TOML input may have",
                    "this is not a configuration file; check the path")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")  # a byte-order mark (some editors add one) is not content
    except UnicodeDecodeError as exc:
        if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):
            raise error(path, "", "UTF-16 text, not UTF-8", "save the file as UTF-8") from None
        line = raw[:exc.start].count(b"\n") + 1
        raise error(path, f"line {line} (byte {exc.start})", "not UTF-8 text",
                    "save the file as UTF-8 (e.g. from Latin-1: iconv -f latin1 -t utf-8)") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(path, "", f"not valid TOML ({exc})", fix_syntax) from None
    except ValueError:  # Python's own limit on the digits of an integer literal
        raise error(path, "", f"an integer literal of more than {sys.get_int_max_str_digits()} digits",
                    "give numbers with a sensible count of digits (TOML integers are 64-bit)") from None
    except RecursionError:
        raise error(path, _deepest_line(text), f"arrays or tables nested more than {MAX_TOML_DEPTH} deep",
                    "flatten the document") from None
    _check_values(doc, path, error, "", 0)
    return doc


def _deepest_line(text):
    """'line N' where brackets first nest beyond the limit (strings ignored: a hint for a document tomllib
    could not even parse)."""
    depth, line = 0, 1
    for char in text:
        if char == "\n":
            line += 1
        elif char in "[{":
            depth += 1
            if depth > MAX_TOML_DEPTH:
                return f"line {line}"
        elif char in "]}":
            depth -= 1
    return ""


def _check_values(value, path, error, where, depth):
    if depth > MAX_TOML_DEPTH:
        raise error(path, f"key '{shown(where, 80, quote=False)}'",
                    f"arrays or tables nested more than {MAX_TOML_DEPTH} deep",
                    "flatten the document")
    if isinstance(value, dict):
        for key, item in value.items():
            if len(key) > MAX_STRING:
                raise error(path, f"key '{shown(key, quote=False)}'", f"a key of {len(key):,} characters",
                            "use a short key")
            _check_values(item, path, error, f"{where}.{key}" if where else key, depth + 1)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            _check_values(item, path, error, f"{where}[{i}]", depth + 1)
    elif isinstance(value, bool):
        return
    elif isinstance(value, int):
        if abs(value) >= _INT_LIMIT:
            raise error(path, f"key '{shown(where, 80, quote=False)}'", "an integer beyond 64 bits",
                        "give a number in range (TOML integers are 64-bit)")
    elif isinstance(value, str) and len(value) > MAX_STRING:
        raise error(path, f"key '{shown(where, 80, quote=False)}'",
                    f"a string of {len(value):,} characters (limit {MAX_STRING:,})",
                    "shorten it")


def name_problem(value, max_length=MAX_NAME):
    """Why ``value`` cannot be a name (one path component), or ``None`` if it can."""
    if not isinstance(value, str):
        return f"a name must be text, got {type(value).__name__}"
    if not value:
        return "empty"
    if len(value) > max_length:
        return f"{len(value):,} characters, more than {max_length}"
    if not value.isprintable():
        return "contains a control character (newline, tab, escape…)"
    if value != value.strip():
        return "starts or ends with a space"
    if any(c in value for c in '/\\:'):
        return "contains a path separator ('/', '\\\\' or ':')"
    if value.startswith("."):
        return "starts with '.'"
    return None


def check_name(value, file, where, what="name", error=InputError, max_length=MAX_NAME, example="'EDU-D3'"):
    """``value`` if it is a safe name, else ``error`` naming the file and the key."""
    problem = name_problem(value, max_length)
    if problem is not None:
        raise error(file, where, f"{what} {shown(value)} cannot be used: {problem}",
                    f"use 1–{max_length} letters, digits, '-', '_', '.', '+' or spaces, e.g. {example}")
    return value


def text_problem(value, max_length=MAX_TEXT):
    """Why ``value`` cannot be printed as one line of free text, or ``None`` if it can."""
    if not isinstance(value, str):
        return f"must be text, got {type(value).__name__}"
    if not value.strip():
        return "empty"
    if len(value) > max_length:
        return f"{len(value):,} characters, more than {max_length}"
    if not value.isprintable():
        return "contains a control character (newline, tab, escape…)"
    return None


def check_text(value, file, where, what="text", error=InputError, max_length=MAX_TEXT):
    """``value`` if it is one printable line of at most ``max_length`` characters, else ``error``."""
    problem = text_problem(value, max_length)
    if problem is not None:
        raise error(file, where, f"{what} {shown(value)} cannot be used: {problem}",
                    f"write one line of at most {max_length} printable characters")
    return value


def shown(value, limit=40, quote=True):
    """``value`` as it may appear in a message: control characters escaped, cut to ``limit`` characters."""
    if not isinstance(value, str):
        return repr(value)[:limit]
    cut = value[:limit] + ("…" if len(value) > limit else "")
    if quote:
        return repr(cut)
    return cut if cut.isprintable() else repr(cut)[1:-1]


def nearest(word, choices):
    """The valid name in ``choices`` closest to ``word`` (case first, then spelling), or ``None``."""
    if not isinstance(word, str):
        return None
    choices = [str(c) for c in choices]
    for c in choices:
        if c.lower() == word.lower():
            return c
    close = difflib.get_close_matches(word, choices, n=1, cutoff=0.6)
    if not close:
        by_lower = {c.lower(): c for c in choices}
        close = [by_lower[m] for m in difflib.get_close_matches(word.lower(), list(by_lower), n=1, cutoff=0.6)]
    return close[0] if close else None


def check_keys(table, valid, file, where="", error=InputError, what="key"):
    """Refuse the first key of ``table`` that is not in ``valid``, naming the nearest valid one.

    ``where`` is the dotted path of the table (``"vehicle"``; ``""`` for the top level).
    """
    for key in table:
        if key in valid:
            continue
        place = f"{where}.{key}" if where else key
        near = nearest(key, valid)
        listed = ", ".join(valid)
        fix = (f"did you mean '{near}'? (valid: {listed})" if near else f"remove it or use one of: {listed}")
        raise error(file, f"key '{shown(place, 80, quote=False)}'", f"unknown {what} {shown(key)}", fix)
    return table


def inside(parent, name):
    """``parent / name`` for a checked name, refusing anything that would leave ``parent`` (defence in depth)."""
    parent = Path(parent)
    problem = name_problem(name, max_length=255)
    child = parent / name
    if problem is not None or child.resolve().parent != parent.resolve():
        raise InputError(parent, f"name {name!r}", f"would place a file outside {parent}",
                         "rename the test, parachute or configuration to a plain name")
    return child


def did_you_mean(name, valid):
    """`` (did you mean 'x'?)`` for the valid name closest to ``name`` (:func:`nearest`), or ``""`` if none is close."""
    near = nearest(str(name), valid)
    return f" (did you mean '{near}'?)" if near else ""


def _json_depth(value, limit):
    """True when ``value`` nests deeper than ``limit`` (iteratively: no recursion to exhaust)."""
    stack = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if depth > limit:
            return True
        if isinstance(item, dict):
            stack.extend((v, depth + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, depth + 1) for v in item)
    return False


def _no_constant(name):
    raise ValueError(f"{name} is not JSON")


def read_json(path, fix, error=InputError, what="JSON file"):
    """The object in JSON file ``path`` (a dict), within the limits above; ``error(path, …, fix)`` otherwise.

    ``fix`` says what rewrites the file (e.g. "re-run 'cpas-bayes fit BUNDLE --out FOLDER'").
    """
    path = Path(path)
    if path.is_dir():
        raise error(path, "", f"is a folder, not a {what}", fix)
    if not path.is_file():
        raise error(path, "", f"{what} not found", fix)
    size = path.stat().st_size
    if size > MAX_JSON_BYTES:
        raise error(path, "", f"{size:,} bytes, more than the {MAX_JSON_BYTES:,} a {what} may have", fix)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(path, f"byte {exc.start}", "not UTF-8 text (a damaged file?)", fix) from None
    if not text.strip():
        raise error(path, "", f"empty (a truncated {what}?)", fix)
    try:
        doc = json.loads(text, parse_constant=_no_constant)
    except (json.JSONDecodeError, ValueError) as exc:
        raise error(path, "", f"not valid JSON ({exc})", fix) from None
    except RecursionError:
        raise error(path, "", f"nested more than {MAX_JSON_DEPTH} deep", fix) from None
    if _json_depth(doc, MAX_JSON_DEPTH):
        raise error(path, "", f"nested more than {MAX_JSON_DEPTH} deep", fix)
    if not isinstance(doc, dict):
        raise error(path, "", f"holds a JSON {type(doc).__name__}, not an object", fix)
    return doc
