"""The model memo: dispersion distributions of inflation parameters for Monte Carlo.

A memo folder holds::

    memo.toml          one entry per parachute kind, stage and parameter
    memo_draws.csv     population-predictive draws, one row per draw of a kind
                       (columns keep the correlations between parameters)
    memo.md            a readable table (written with the memo by cpas_bayes.outputs.memo)

memo.toml layout::

    [provenance]
    package_version = "0.1.0"
    created = "2026-11-21T12:00:00Z"
    tests = ["CDT-1", "CDT-2", ...]
    seeds = [0, 0, ...]
    method = "..."

    [drogue.first.n_p]                 # kind . stage key . parameter
    family = "lognormal"               # normal | truncnormal | lognormal | beta | uniform
    params = { median = 10.2, sigma_log = 0.12 }
    bounds = [2.0, 50.0]
    quantiles = { q01 = 7.8, q05 = 8.4, q50 = 10.2, q95 = 12.4, q99 = 13.3 }
    n_tests = 8
    criterion = { name = "loo_test", values = { normal = -12.3, lognormal = -11.9 } }

    [drogue.parachute.cd_o]            # per-canopy quantities use stage key "parachute"

An entry's ``family`` and ``params`` are a table of
:mod:`cpas_bayes.stats.distributions` (:meth:`MemoEntry.distribution`); its
``bounds`` are a truncnormal's truncation and a beta's range, and every
family's draws are clipped to them.

Stage keys are those of :func:`cpas_bayes.physics.inflation.stage_key`: ``first``,
``reefed1``…, ``full_open``. Parameters: ``n_p``, ``n``, ``expopen``, ``ck``,
``tk``, ``eps`` per stage, ``cd_o`` per canopy, and ``t_fp`` (peak fill time
seen in the tests, s; its ``bounds`` are the range the tests showed).

``memo_draws.csv`` columns: ``kind`` then ``<stage>.<parameter>`` (and
``parachute.cd_o``); a column is empty for a kind that lacks it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_path, write_text
from cpas_bayes.core.inputs import check_name, did_you_mean, read_toml
from cpas_bayes.stats.distributions import TABLE_FORMS, Distribution, from_table

MEMO_NAME = "memo.toml"
DRAWS_NAME = "memo_draws.csv"
FAMILIES = ("normal", "truncnormal", "lognormal", "beta", "uniform")   # the order memo files list them


@dataclass(frozen=True)
class MemoEntry:
    """Population distribution of one parameter of one parachute kind and stage."""

    kind: str
    stage: str
    parameter: str
    family: str
    params: dict
    bounds: tuple = (-math.inf, math.inf)
    quantiles: dict = field(default_factory=dict)
    n_tests: int = 0
    criterion: dict = field(default_factory=dict)

    def distribution(self) -> Distribution:
        """The entry's frozen distribution (:mod:`cpas_bayes.stats.distributions`): ``params``, with
        ``bounds`` as the truncation of a truncnormal and the range of a beta."""
        table = {"family": self.family, **self.params}
        if self.family in ("truncnormal", "beta"):
            table["low"], table["high"] = self.bounds
        return from_table(table)

    def sample(self, rng, size):
        """Independent draws (inverse transform of ``rng.uniform``), clipped to the entry's bounds."""
        return np.clip(self.distribution().sample(rng, size), *self.bounds)

    def to_table(self):
        out = {"family": self.family, "params": dict(self.params),
               "bounds": [_finite_or_str(b) for b in self.bounds],
               "quantiles": dict(self.quantiles), "n_tests": int(self.n_tests)}
        if self.criterion:
            out["criterion"] = self.criterion
        return out


def _finite_or_str(x):
    return float(x) if math.isfinite(x) else ("inf" if x > 0 else "-inf")


@dataclass
class Memo:
    """Entries {(kind, stage, parameter): MemoEntry}, joint draws and provenance."""

    entries: dict
    draws: pd.DataFrame
    provenance: dict
    folder: Path | None = None

    def kinds(self):
        return sorted({k for k, _, _ in self.entries})

    def entry(self, kind, stage, parameter):
        try:
            return self.entries[(kind, stage, parameter)]
        except KeyError:
            where = self.folder / MEMO_NAME if self.folder else MEMO_NAME
            raise InputError(where, f"key '{kind}.{stage}.{parameter}'", "the memo has no such entry",
                             "pool tests of this parachute kind and stage into the memo first") from None

    def sample(self, kind, n, rng, joint=True):
        """``n`` parameter sets of parachute ``kind``: a DataFrame with ``<stage>.<parameter>`` columns.

        ``joint=True`` resamples rows of the population-predictive draws, which
        keeps correlations (n_p with expopen, say); ``joint=False`` draws every
        column independently from its family, the classic dispersion practice.
        """
        if joint:
            rows = self.draws[self.draws["kind"] == kind].drop(columns="kind").dropna(axis=1, how="all")
            if rows.empty:
                raise InputError(self.folder / DRAWS_NAME if self.folder else DRAWS_NAME, f"kind '{kind}'",
                                 "no population draws for this parachute kind",
                                 "pool tests of this kind into the memo first")
            pick = rng.integers(0, len(rows), size=n)
            return rows.iloc[pick].reset_index(drop=True)
        cols = {f"{stage}.{param}": e.sample(rng, n) for (k, stage, param), e in sorted(self.entries.items())
                if k == kind}
        if not cols:
            raise InputError(self.folder / MEMO_NAME if self.folder else MEMO_NAME, f"kind '{kind}'",
                             "no entries for this parachute kind", "pool tests of this kind into the memo first")
        return pd.DataFrame(cols)

    def write(self, folder):
        """Write memo.toml and memo_draws.csv into ``folder`` (atomically, file by file)."""
        folder = Path(folder)
        doc = {"provenance": self.provenance}
        for (kind, stage, param), e in sorted(self.entries.items()):
            doc.setdefault(kind, {}).setdefault(stage, {})[param] = e.to_table()
        write_text(folder / MEMO_NAME, tomli_w.dumps(doc))
        with atomic_path(folder / DRAWS_NAME) as tmp:
            self.draws.to_csv(tmp, index=False, float_format="%.10g")
        return folder / MEMO_NAME


def _repool(folder):
    return (f"re-run 'cpas-bayes pool FITDIR... --out {folder}' to rewrite the memo (in a campaign: delete "
            f"{folder} and re-run the campaign)")


def load_memo(path) -> Memo:
    """Read a memo from its memo.toml (or the folder holding it), refusing a damaged or hand-broken one.

    Every entry must be a table with a known ``family``, the ``params`` that
    family needs as finite numbers (scales positive), ``bounds`` [low, high]
    with low < high, and a distribution whose quantiles are finite;
    ``memo_draws.csv`` must be a table with ``kind`` and ``<stage>.<parameter>``
    columns of finite numbers for the kinds of memo.toml (a column empty for a
    kind that lacks it). A refusal names the file, the key or the row and
    column, and says to re-run ``cpas-bayes pool``.
    """
    path = Path(path)
    if path.is_dir():
        path = path / MEMO_NAME
    if not path.is_file():
        raise InputError(path, "", "memo file not found", "pass a memo.toml written by 'cpas-bayes pool'")
    # re-pooling into the file's folder is the fix only where that folder is a memo's: never a fit folder's
    fix = _repool(path.parent) if path.name == MEMO_NAME else (
        f"pass a {MEMO_NAME} written by 'cpas-bayes pool' (or its folder); {path.name} is not one")
    try:
        doc = read_toml(path)
    except InputError as exc:   # the same problem, with what rewrites a memo as the fix
        raise InputError(exc.file, exc.where, exc.problem, fix) from None
    provenance = doc.get("provenance", {})
    if not isinstance(provenance, dict):
        raise InputError(path, "key 'provenance'", "must be a table", fix)
    entries = {}
    for kind, stages in doc.items():
        if kind == "provenance":
            continue
        check_name(kind, path, f"key '{kind}'", "parachute kind")
        if not isinstance(stages, dict):
            raise InputError(path, f"key '{kind}'", "must be a table of stages ([kind.stage.parameter])", fix)
        for stage, params in stages.items():
            if not isinstance(params, dict) or not _STAGE_KEY.fullmatch(stage):
                problem = ("must be a table of parameters" if _STAGE_KEY.fullmatch(stage) else
                           f"unknown stage '{stage}'{did_you_mean(stage, ('first', 'reefed1', 'full_open', 'parachute'))}; "
                           "stages are first, reefed1, reefed2…, full_open and parachute")
                raise InputError(path, f"key '{kind}.{stage}'", problem, fix)
            for param, table in params.items():
                entries[(kind, stage, param)] = _entry(path, kind, stage, param, table, fix)
    if not entries:
        raise InputError(path, "", "no entries ([kind.stage.parameter] tables)", fix)
    draws = _read_draws(path.parent / DRAWS_NAME, entries, fix)
    return Memo(entries, draws, provenance, path.parent)


_STAGE_KEY = re.compile(r"first|reefed[1-9][0-9]*|full_open|parachute")
PARAMETERS = ("n_p", "n", "expopen", "ck", "tk", "eps", "cd_o", "t_fp")
_ENTRY_KEYS = ("family", "params", "bounds", "quantiles", "n_tests", "criterion")
_POSITIVE = ("sigma", "sigma_log", "a", "b", "median")
MAX_DRAWS_BYTES = 500_000_000


def _number(value):
    """``value`` as a float if it is a real number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value)


def _bound(value):
    if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "-inf"):
        return float(value)
    return _number(value)


def _entry(path, kind, stage, param, t, fix) -> MemoEntry:
    """One memo.toml entry, checked (see :func:`load_memo`)."""
    where = f"key '{kind}.{stage}.{param}'"
    if param not in PARAMETERS:
        raise InputError(path, where, f"unknown parameter '{param}'{did_you_mean(param, PARAMETERS)}; "
                         f"use one of {', '.join(PARAMETERS)}", fix)
    if not isinstance(t, dict):
        raise InputError(path, where, f"must be a table with family, params and bounds, got {t!r:.60}", fix)
    unknown = [k for k in t if k not in _ENTRY_KEYS]
    if unknown:
        raise InputError(path, f"key '{kind}.{stage}.{param}.{unknown[0]}'",
                         f"unknown key{did_you_mean(unknown[0], _ENTRY_KEYS)}; an entry has {', '.join(_ENTRY_KEYS)}", fix)
    family = t.get("family")
    if family not in FAMILIES:
        shown = f"{family!r}{did_you_mean(family, FAMILIES)}" if isinstance(family, str) else repr(family)
        raise InputError(path, f"{where[:-1]}.family'", f"unknown family {shown}; use one of {', '.join(FAMILIES)}",
                         fix)
    cls, required, optional = TABLE_FORMS[family]
    from_bounds = ("low", "high") if family in ("truncnormal", "beta") else ()
    needed = [n for n in required if n not in from_bounds]
    params = t.get("params")
    if not isinstance(params, dict):
        problem = "missing" if params is None else f"must be a table of numbers, got {params!r:.60}"
        raise InputError(path, f"{where[:-1]}.params'", f"{problem} (a {family} entry needs {', '.join(needed)})", fix)
    values = {}
    for name, value in params.items():
        if name not in required + optional + ("low", "high"):
            raise InputError(path, f"{where[:-1]}.params.{name}'", f"not a number of a {family} distribution "
                             f"(it has {', '.join(needed)})", fix)
        x = _number(value)
        if x is None or not math.isfinite(x):
            raise InputError(path, f"{where[:-1]}.params.{name}'", f"must be a finite number, got {value!r:.60}", fix)
        if name in _POSITIVE and not x > 0:
            raise InputError(path, f"{where[:-1]}.params.{name}'", f"must be positive, got {x:g}", fix)
        values[name] = x
    missing = [n for n in needed if n not in values]
    if missing:
        raise InputError(path, f"{where[:-1]}.params.{missing[0]}'", f"missing (a {family} entry needs "
                         f"{', '.join(needed)})", fix)
    raw_bounds = t.get("bounds", ["-inf", "inf"])
    bounds = [_bound(b) for b in raw_bounds] if isinstance(raw_bounds, list) and len(raw_bounds) == 2 else None
    if bounds is None or any(b is None or math.isnan(b) for b in bounds):
        raise InputError(path, f"{where[:-1]}.bounds'", f"must be [low, high] with numbers (or \"-inf\"/\"inf\"), "
                         f"got {raw_bounds!r:.60}", fix)
    if not bounds[0] < bounds[1]:
        raise InputError(path, f"{where[:-1]}.bounds'", f"low {bounds[0]:g} is not below high {bounds[1]:g}", fix)
    if family == "beta" and not all(math.isfinite(b) for b in bounds):
        raise InputError(path, f"{where[:-1]}.bounds'", "a beta entry's bounds are its finite range", fix)
    if family == "uniform" and not values["low"] < values["high"]:
        raise InputError(path, f"{where[:-1]}.params'", f"low {values['low']:g} is not below high "
                         f"{values['high']:g}", fix)
    quantiles = t.get("quantiles", {})
    if not isinstance(quantiles, dict) or any(_number(v) is None or not math.isfinite(_number(v))
                                              for v in quantiles.values()):
        raise InputError(path, f"{where[:-1]}.quantiles'", "must be a table of finite numbers", fix)
    n_tests = t.get("n_tests", 0)
    if isinstance(n_tests, bool) or not isinstance(n_tests, int) or n_tests < 0:
        raise InputError(path, f"{where[:-1]}.n_tests'", f"must be a whole number ≥ 0, got {n_tests!r:.60}", fix)
    criterion = t.get("criterion", {})
    if not isinstance(criterion, dict):
        raise InputError(path, f"{where[:-1]}.criterion'", "must be a table", fix)
    entry = MemoEntry(kind, stage, param, family, values, tuple(bounds), dict(quantiles), n_tests, dict(criterion))
    try:
        with np.errstate(all="ignore"):
            q = np.asarray(entry.distribution().ppf(np.array([1e-3, 0.5, 1 - 1e-3])), float)
        ok = bool(np.all(np.isfinite(q)))
    except (ValueError, ZeroDivisionError, OverflowError, TypeError):
        ok = False
    if not ok:
        raise InputError(path, where, f"its {family} distribution (params {values}, bounds {list(bounds)}) has no "
                         "finite quantiles", fix)
    return entry


def _read_draws(path, entries, fix) -> pd.DataFrame:
    """memo_draws.csv, checked against the memo's entries (see :func:`load_memo`)."""
    if not path.is_file():
        raise InputError(path, "", "population draws missing beside the memo", fix)
    size = path.stat().st_size
    if size > MAX_DRAWS_BYTES:
        raise InputError(path, "", f"{size:,} bytes, more than the {MAX_DRAWS_BYTES:,} a memo's draws may have",
                         fix)
    try:
        draws = pd.read_csv(path, dtype={"kind": str})
    except pd.errors.EmptyDataError:
        raise InputError(path, "", "empty (no header, no rows)", fix) from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, "", f"not a CSV table ({str(exc).strip()[:120]})", fix) from None
    if "kind" not in draws.columns:
        raise InputError(path, "column 'kind'", "missing", fix)
    if draws.empty:
        raise InputError(path, "", "no rows of draws", fix)
    kinds = {k for k, _, _ in entries}
    labels = draws["kind"]
    for i, kind in enumerate(labels):
        if not isinstance(kind, str) or kind not in kinds:
            raise InputError(path, f"row {i + 2}, column 'kind'", f"kind {kind!r} has no entries in {MEMO_NAME}", fix)
    for column in draws.columns:
        if column == "kind":
            continue
        stage, _, param = str(column).partition(".")
        if not _STAGE_KEY.fullmatch(stage) or param not in PARAMETERS:
            raise InputError(path, f"column '{column}'", "not a <stage>.<parameter> column (e.g. first.n_p)", fix)
        raw = draws[column]
        numeric = pd.api.types.is_numeric_dtype(raw) and not pd.api.types.is_bool_dtype(raw)
        values = raw.astype(float) if numeric else pd.to_numeric(raw.astype(object), errors="coerce")
        bad = (values.isna() & raw.notna()) | np.isinf(values)
        if bad.any():
            i = int(np.argmax(bad.to_numpy()))
            raise InputError(path, f"row {i + 2}, column '{column}'", f"{raw.iloc[i]!r:.40} is not a finite number",
                             fix)
        for kind in sorted(set(labels)):
            rows = (labels == kind).to_numpy()
            empty = values[rows].isna().to_numpy()
            if empty.all():
                continue
            if empty.any():
                i = int(np.flatnonzero(rows)[np.argmax(empty)])
                raise InputError(path, f"row {i + 2}, column '{column}'", f"empty for kind '{kind}', which has draws "
                                 "of it in other rows", fix)
            if (kind, stage, param) not in entries:
                raise InputError(path, f"column '{column}'", f"draws for kind '{kind}', but {MEMO_NAME} has no entry "
                                 f"'{kind}.{stage}.{param}'", fix)
        draws[column] = values.astype(float)
    return draws
