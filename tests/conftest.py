"""Shared fixtures: copies of the example bundles, bundle-file editing, folder snapshots.

Fixtures that hypothesis tests use are session-scoped (they hold no state), since
function-scoped fixtures are not reset between hypothesis examples.
"""

from __future__ import annotations

import os
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from cpas_bayes.data.bundle import CSV_NAME, EXAMPLES_DIR, TOML_NAME

# Figures go to files in the tests, also where a display exists (the library never picks a backend).
os.environ.setdefault("MPLBACKEND", "Agg")

N_PER_LBF = 4.4482216152605
M_PER_FT = 0.3048
# Hand-computed factors from a US bundle's units to SI, by quantity (1 slug = 1 lbf s²/ft).
US_TO_SI = {"force": N_PER_LBF, "length": M_PER_FT, "area": M_PER_FT**2, "speed": M_PER_FT,
            "pressure": 47.880258980336, "density": N_PER_LBF / M_PER_FT**4, "time": 1.0}


class BundleFiles:
    """Read-modify-write access to one bundle folder's test.toml and data.csv.

    CSV rows are lists of cell strings; ``row`` numbers are 1-based file lines,
    so the header is row 1 and the first data row is row 2.
    """

    def __init__(self, folder):
        self.folder = Path(folder)
        self.toml_path = self.folder / TOML_NAME
        self.csv_path = self.folder / CSV_NAME

    # test.toml
    def read_toml(self):
        return tomllib.loads(self.toml_path.read_text(encoding="utf-8"))

    def write_toml(self, doc):
        self.toml_path.write_text(tomli_w.dumps(doc), encoding="utf-8")

    def set_key(self, *path, value):
        """Set the value at ``path``, e.g. ``set_key("parachute", 0, "kind", value="x")``."""
        doc = self.read_toml()
        *parents, last = path
        node = doc
        for key in parents:
            node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
        node[last] = value
        self.write_toml(doc)

    def delete_key(self, *path):
        doc = self.read_toml()
        *parents, last = path
        node = doc
        for key in parents:
            node = node[key]
        del node[last]
        self.write_toml(doc)

    # data.csv
    def read_rows(self):
        return [line.split(",") for line in self.csv_path.read_text(encoding="utf-8").splitlines()]

    def write_rows(self, rows):
        self.csv_path.write_text("".join(",".join(row) + "\n" for row in rows), encoding="utf-8")

    def header(self):
        return self.read_rows()[0]

    def cell(self, row, column):
        rows = self.read_rows()
        return rows[row - 1][rows[0].index(column)]

    def set_cell(self, row, column, text):
        rows = self.read_rows()
        rows[row - 1][rows[0].index(column)] = text
        self.write_rows(rows)

    def drop_column(self, column):
        rows = self.read_rows()
        i = rows[0].index(column)
        self.write_rows([row[:i] + row[i + 1:] for row in rows])

    def rename_column(self, old, new):
        rows = self.read_rows()
        rows[0][rows[0].index(old)] = new
        self.write_rows(rows)


def folder_state(root):
    """Every path under ``root`` with its bytes (None for folders): equal states mean nothing was written."""
    return {p.relative_to(root).as_posix(): p.read_bytes() if p.is_file() else None
            for p in sorted(Path(root).rglob("*"))}


def assert_same_test(actual, expected, rtol=1e-9):
    """Two FlightTests hold the same metadata and time histories (floats to ``rtol``)."""
    assert (actual.name, actual.phase, actual.units.name) == (expected.name, expected.phase, expected.units.name)
    np.testing.assert_allclose(
        [actual.vehicle.weight, actual.vehicle.weight_sigma, actual.vehicle.cds, actual.vehicle.cds_sigma],
        [expected.vehicle.weight, expected.vehicle.weight_sigma, expected.vehicle.cds, expected.vehicle.cds_sigma],
        rtol=rtol)
    assert len(actual.parachutes) == len(expected.parachutes)
    for a, e in zip(actual.parachutes, expected.parachutes):
        assert (a.id, a.kind, a.inflation, a.load_cell, a.flyout_angle) == \
            (e.id, e.kind, e.inflation, e.load_cell, e.flyout_angle)
        np.testing.assert_allclose([a.diameter, a.weight, a.weight_sigma], [e.diameter, e.weight, e.weight_sigma],
                                   rtol=rtol)
        assert [s.label for s in a.stages] == [s.label for s in e.stages]
        np.testing.assert_allclose([(s.start, s.start_sigma) for s in a.stages],
                                   [(s.start, s.start_sigma) for s in e.stages], rtol=rtol)
    assert list(actual.data.columns) == list(expected.data.columns)
    np.testing.assert_allclose(actual.data.to_numpy(), expected.data.to_numpy(), rtol=rtol, atol=0)


@pytest.fixture
def example_dir(tmp_path):
    """``example_dir(name, copy_name=None)``: copy example bundle ``name`` into tmp_path; return the copy."""
    def copy(name, copy_name=None):
        return Path(shutil.copytree(EXAMPLES_DIR / name, tmp_path / (copy_name or name)))
    return copy


@pytest.fixture(scope="session")
def bundle_files():
    """The :class:`BundleFiles` class: ``bundle_files(folder)`` edits that bundle."""
    return BundleFiles


@pytest.fixture(scope="session")
def snapshot():
    """``snapshot(root)``: :func:`folder_state` of a folder tree."""
    return folder_state


@pytest.fixture(scope="session")
def same_test():
    """``same_test(actual, expected, rtol=1e-9)``: :func:`assert_same_test`."""
    return assert_same_test


@pytest.fixture(scope="session")
def us_to_si():
    """Hand-computed factors from US bundle units to SI, by quantity."""
    return dict(US_TO_SI)
