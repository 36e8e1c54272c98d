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
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from cpas_bayes.core.errors import InputError
from cpas_bayes.core.files import atomic_path, write_text
from cpas_bayes.stats.distributions import Distribution, from_table

MEMO_NAME = "memo.toml"
DRAWS_NAME = "memo_draws.csv"
FAMILIES = ("normal", "truncnormal", "lognormal", "beta", "uniform")


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


def load_memo(path) -> Memo:
    """Read a memo from its memo.toml (or the folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / MEMO_NAME
    if not path.is_file():
        raise InputError(path, "", "memo file not found", "pass a memo.toml written by 'cpas-bayes pool'")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, "", f"not valid TOML ({exc})", "rewrite it with 'cpas-bayes pool'") from None
    entries = {}
    for kind, stages in doc.items():
        if kind == "provenance":
            continue
        for stage, params in stages.items():
            for param, t in params.items():
                where = f"key '{kind}.{stage}.{param}'"
                if t.get("family") not in FAMILIES:
                    raise InputError(path, where, f"unknown family {t.get('family')!r}",
                                     f"use one of {', '.join(FAMILIES)}")
                bounds = tuple(float(b) for b in t.get("bounds", ["-inf", "inf"]))
                entries[(kind, stage, param)] = MemoEntry(
                    kind, stage, param, t["family"], dict(t.get("params", {})), bounds,
                    dict(t.get("quantiles", {})), int(t.get("n_tests", 0)), dict(t.get("criterion", {})))
    draws_path = path.parent / DRAWS_NAME
    if not draws_path.is_file():
        raise InputError(draws_path, "", "population draws missing beside the memo",
                         "rewrite the memo with 'cpas-bayes pool'")
    draws = pd.read_csv(draws_path)
    if "kind" not in draws.columns:
        raise InputError(draws_path, "column 'kind'", "missing", "rewrite the memo with 'cpas-bayes pool'")
    return Memo(entries, draws, doc.get("provenance", {}), path.parent)
