"""A bundle written by hand for the tests: test.toml from a dict, data.csv from rows (dicts) with empty cells
for the keys a row lacks (a logger's blank cells between a receiver's samples)."""

import tomli_w


def write_by_hand(folder, doc, rows, header):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "test.toml").write_text(tomli_w.dumps(doc), encoding="utf-8")
    lines = [",".join(header)] + [",".join(repr(r[c]) if c in r else "" for c in header) for r in rows]
    (folder / "data.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return folder
