"""Reading a bundle's data.csv within stated limits: size, header, row shape, numeric cells; and passing a
CSV file's leading lines without reading them whole (:func:`skip_lines`, for an import map's ``skip_rows``);
which folders are bundles (:func:`bundle_folders`).

The file's size and row count are checked before it is parsed, the header
before any row, and every row's cell count against the header's (a trailing
comma on every row is said as such: pandas would otherwise take the first
column as an index and shift every name by one). Cells stay text until a
column is used, so a bad cell is reported by its row and column.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pandas as pd

from cpas_bayes.core.errors import BundleError
from cpas_bayes.core.inputs import not_a_file, shown, text_problem
from cpas_bayes.data.limits import MAX_COLUMN_NAME, MAX_CSV_BYTES, MAX_CSV_COLUMNS, MAX_CSV_ROWS

TOML_NAME, CSV_NAME = "test.toml", "data.csv"   # a bundle folder's two files
_HEADER_FIX = "start data.csv with a comma-separated header such as time,G,G_sigma,..."
_TRAILING_FIX = "remove the comma at the end of every line (an export option of the spreadsheet or logger)"


def bundle_folders(folder) -> list:
    """The bundle folders ``folder`` names: itself when it holds a test.toml, else its sub-folders that do (a
    folder of bundles, a campaign's), sorted; none when it is not a folder."""
    folder = Path(folder)
    if (folder / TOML_NAME).is_file():
        return [folder]
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_dir() and (p / TOML_NAME).is_file())


def _missing(path, other):
    problem = not_a_file(path)
    if problem:   # there, but a folder, a pipe, a device or a broken link
        return BundleError(path, "", problem, f"put the bundle's {path.name} there as a plain file")
    return BundleError(path, "", "file not found", f"a bundle folder needs {other} and {path.name} "
                                                   "(docs/test-bundle.md)")


def _check_header(path, names):
    if len(names) > MAX_CSV_COLUMNS:
        raise BundleError(path, "row 1 (header)", f"{len(names):,} columns, more than {MAX_CSV_COLUMNS:,}",
                          "keep the channels the bundle format uses (docs/test-bundle.md)")
    if names == [""]:
        raise BundleError(path, "row 1 (header)", "the header row is missing or empty", _HEADER_FIX)
    if len(names) == 1 and any(sep in names[0] for sep in (";", "\t")):
        sep = "semicolons" if ";" in names[0] else "tabs"
        raise BundleError(path, "row 1 (header)", f"the columns are separated by {sep}, not commas",
                          "export data.csv with commas between cells and points as decimal marks "
                          "(a spreadsheet's 'CSV, comma-separated' with an English number format)")
    if len(names) > 1 and names[-1] == "":
        raise BundleError(path, f"row 1 (header), column {len(names)}",
                          "the header ends with a comma: an unnamed empty last column", _TRAILING_FIX)
    for k, name in enumerate(names):
        if name == "":
            raise BundleError(path, f"row 1 (header), column {k + 1}", "a column has no name",
                              "name every column, or remove the empty one")
        problem = text_problem(name, MAX_COLUMN_NAME)
        if problem:
            raise BundleError(path, f"row 1 (header), column {k + 1}", f"column name {shown(name)}: {problem}",
                              f"use names of at most {MAX_COLUMN_NAME} printable characters")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise BundleError(path, f"column '{dupes[0]}'", "column name appears more than once",
                          "give every column a unique name")


def _check_row_shapes(path, raw, n_columns):
    """Refuse rows with more cells than the header (fewer cells are empty cells, reported where used)."""
    data = np.frombuffer(raw, dtype=np.uint8)
    newlines = np.flatnonzero(data == 10)
    ends = np.append(newlines, len(data)) if not raw.endswith(b"\n") else newlines
    commas = np.searchsorted(np.flatnonzero(data == 44), ends)
    cells = np.diff(np.concatenate([[0], commas])) + 1              # cells per line, header first
    longer = np.flatnonzero(cells[1:] > n_columns)
    if not longer.size:
        return
    i = int(longer[0]) + 1                                           # 0-based line index
    start = int(ends[i - 1]) + 1
    line = raw[start:int(ends[i])].decode("utf-8", "replace").rstrip("\r")
    extra = line.split(",")[n_columns:]
    row = f"row {i + 1}"
    if all(not c.strip() for c in extra):
        every = " (every data row does)" if (cells[1:] > n_columns).all() else ""
        raise BundleError(path, row, f"the row ends with a comma{every}: {len(extra)} empty cell(s) beyond the "
                          f"header's {n_columns} columns", _TRAILING_FIX)
    raise BundleError(path, row, f"{int(cells[i])} cells, but the header names {n_columns} columns",
                      "make every row have as many comma-separated cells as the header")


def read_csv(path, toml_name=TOML_NAME):
    """data.csv as a frame of cell strings (header names stripped); refuses with file, row and fix."""
    if not path.is_file():
        raise _missing(path, toml_name)
    size = path.stat().st_size
    if size > MAX_CSV_BYTES:
        raise BundleError(path, "", f"{size:,} bytes, more than the {MAX_CSV_BYTES:,} a data.csv may have",
                          "split the record into one bundle per phase, or drop unused columns and samples")
    raw = path.read_bytes()
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    n_lines = raw.count(b"\n") + (0 if raw.endswith(b"\n") or not raw else 1)
    if n_lines - 1 > MAX_CSV_ROWS:
        raise BundleError(path, "", f"{n_lines - 1:,} data rows, more than {MAX_CSV_ROWS:,}",
                          "split the record into one bundle per phase, or resample it")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BundleError(path, f"byte {exc.start}", "not UTF-8 text", "save data.csv as UTF-8 CSV") from None
    header = text.partition("\n")[0].strip()
    names = [h.strip() for h in header.split(",")]
    _check_header(path, names)
    _check_row_shapes(path, raw.rstrip(b"\r\n"), len(names))
    try:
        # Blank lines stay rows so that row numbers are file lines; only trailing ones are dropped.
        frame = pd.read_csv(io.StringIO(text.rstrip("\r\n")), dtype=str, skipinitialspace=True, index_col=False,
                            keep_default_na=False, skip_blank_lines=False)
    except (pd.errors.ParserError, ValueError) as exc:
        raise BundleError(path, "", f"not a readable CSV table ({exc})",
                          "make every row have as many comma-separated cells as the header") from None
    frame.columns = [c.strip() for c in frame.columns]
    if frame.empty:
        raise BundleError(path, "", "has a header but no data rows", "add at least two rows of samples")
    return frame


def parse_numbers(frame, column):
    """One text column as floats, and the index and text of its first empty, non-numeric or non-finite
    cell (None, None when every cell is a finite number)."""
    raw = frame[column].str.strip()
    values = pd.to_numeric(raw, errors="coerce").to_numpy(dtype=float)
    bad = ~np.isfinite(values)
    if not bad.any():
        return values, None, None
    i = int(np.flatnonzero(bad)[0])
    return values, i, raw.iloc[i]


def _bad_cell(path, column, i, cell, value, fix):
    what = "is empty" if cell == "" else (f"is not a number ({shown(cell)})" if np.isnan(value) and
                                          cell.lower() not in ("nan", "-nan", "+nan") else
                                          f"is {shown(cell)}, not a finite number")
    return BundleError(path, f"row {i + 2}, column '{column}'", f"the cell {what}", fix)


def numeric_column(frame, column, path):
    """The finite numbers of one column; refuses the first empty, non-numeric or non-finite cell."""
    values, i, cell = parse_numbers(frame, column)
    if i is not None:
        raise _bad_cell(path, column, i, cell, values[i],
                        "every cell of a used column must hold a finite number; remove or repair the row")
    return values


def blank_column(frame, column, path):
    """One column whose empty cells are missing samples (NaN); refuses the first non-numeric or non-finite
    cell (a written ``nan`` too: a gap is an empty cell)."""
    raw = frame[column].fillna("").str.strip()
    blank = (raw == "").to_numpy()
    values = pd.to_numeric(raw.mask(blank, "0"), errors="coerce").to_numpy(dtype=float, copy=True)
    bad = np.flatnonzero(~np.isfinite(values))
    if bad.size:
        i = int(bad[0])
        raise _bad_cell(path, column, i, raw.iloc[i], values[i],
                        "a cell holds a finite number, or is empty where the channel has no sample")
    values[blank] = np.nan
    return values


def csv_header(path):
    """data.csv's column names from a look at its first line, or None when the file is missing or unreadable
    (:func:`read_csv` then says why)."""
    if not path.is_file():    # a FIFO or device would block the read; read_csv refuses it
        return None
    try:
        with open(path, "rb") as fh:
            line = fh.readline(MAX_CSV_COLUMNS * (MAX_COLUMN_NAME + 2))   # a longer header is refused anyway
    except OSError:
        return None
    try:
        text = line.removeprefix(b"\xef\xbb\xbf").decode("utf-8")
    except UnicodeDecodeError:
        return None
    return [h.strip() for h in text.strip().split(",")]


def sigma_column(frame, column, sigma_table, path):
    """Per-sample sigma of ``column``: its ``<column>_sigma`` or the constant [sigma] entry, else ``None``."""
    name = f"{column}_sigma"
    if name in frame.columns:
        values = numeric_column(frame, name, path)
        if (values < 0).any():
            i = int(np.flatnonzero(values < 0)[0])
            raise BundleError(path, f"row {i + 2}, column '{name}'", f"negative sigma {values[i]}",
                              "a 1-sigma is ≥ 0; correct the value")
        return values
    if column in sigma_table:
        return np.full(len(frame), float(sigma_table[column]))
    return None


_LINE_END = re.compile(rb"\r\n|\r|\n")   # pandas' C parser ends a line at any of them
_CHUNK = 1 << 20


def skip_lines(handle, n):
    """Pass ``n`` lines of a binary file from its start: (byte offset after them, lines passed).

    Streams 1 MB at a time, so memory does not grow with the file or with ``n``; fewer than ``n`` lines
    passed means the file ended first. The handle's position is left undefined: seek to the offset.
    """
    offset = seen = 0
    carry = b""
    handle.seek(0)
    while seen < n:
        data = handle.read(_CHUNK)
        chunk, carry = carry + data, b""
        if not chunk:
            break
        if data and chunk.endswith(b"\r"):   # its \n may open the next chunk: one line end, not two
            chunk, carry = chunk[:-1], b"\r"
        ends = chunk.count(b"\n") + chunk.count(b"\r") - chunk.count(b"\r\n")
        if seen + ends < n:
            seen, offset = seen + ends, offset + len(chunk)
            continue
        for match in _LINE_END.finditer(chunk):
            seen += 1
            if seen == n:
                return offset + match.end(), seen
    return offset, seen
