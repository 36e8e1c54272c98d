"""core.inputs: TOML within stated limits, names that stay one path component, printable text,
unknown keys refused with the nearest valid one, and messages that never carry a control character."""

from __future__ import annotations

import string

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cpas_bayes.core import inputs
from cpas_bayes.core.errors import BundleError, InputError
from cpas_bayes.core.inputs import check_keys, check_name, check_text, inside, nearest, read_toml, shown

SETTINGS = dict(deadline=None, derandomize=True, database=None)


# ---------------------------------------------------------------------------
# read_toml

def test_a_byte_order_mark_is_not_content(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbfname = \"x\"\n")
    assert read_toml(path) == {"name": "x"}


READ_REFUSALS = [
    # id, bytes, place named (None: the file only), problem named
    ("400-digit integer", b"a = " + b"9" * 400 + b"\n", "key 'a'", "an integer beyond 64 bits"),
    ("5000-digit integer", b"a = " + b"9" * 5000 + b"\n", None, "an integer literal of more than"),
    ("100,000-deep array", b"b = 1\na = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", "line 2", "nested more than 16"),
    ("deep inline tables", b"a = " + b"{b = " * 40 + b"1" + b"}" * 40 + b"\n", "key 'a.b.b.b", "nested more"),
    ("Latin-1", "a = 1\nlabel = \"caf\xe9\"\n".encode("latin-1"), "line 2 (byte 18)", "not UTF-8 text"),
    ("UTF-16", "a = 1\n".encode("utf-16"), None, "UTF-16 text, not UTF-8"),
    ("long string", b"a = \"" + b"x" * 20_000 + b"\"\n", "key 'a'", "a string of 20,000 characters"),
    ("syntax", b"a = = 1\n", None, "not valid TOML"),
    ("escape in a key", b"[\"\\u001b[31m\"]\nb = " + b"9" * 30 + b"\n", "key '\\x1b[31m.b'", "beyond 64 bits"),
]


@pytest.mark.parametrize("content, place, problem", [c[1:] for c in READ_REFUSALS], ids=[c[0] for c in READ_REFUSALS])
def test_read_toml_refusals_name_the_file_and_place(tmp_path, content, place, problem):
    path = tmp_path / "in.toml"
    path.write_bytes(content)
    with pytest.raises(BundleError) as info:
        read_toml(path, error=BundleError)
    message = str(info.value)
    assert message.startswith(f"{path}{', ' + place if place else ''}"), message
    assert problem in message and ". Fix: " in message
    assert "\x1b" not in message


def test_read_toml_size_limit_and_missing_file(tmp_path, monkeypatch):
    path = tmp_path / "big.toml"
    path.write_text("a = 1\n" * 10)
    monkeypatch.setattr(inputs, "MAX_TOML_BYTES", 20)
    with pytest.raises(InputError, match=r"60 bytes, more than the 20"):
        read_toml(path)
    with pytest.raises(InputError, match="file not found"):
        read_toml(tmp_path / "absent.toml")
    with pytest.raises(InputError, match="is a folder"):
        read_toml(tmp_path)


# ---------------------------------------------------------------------------
# names and text

@pytest.mark.parametrize("name", ["EDU-D3", "CDT-3-2 drogue", "D3.1", "Düse+2", "x" * 64])
def test_good_names(name):
    assert check_name(name, "f.toml", "key 'name'") == name


@pytest.mark.parametrize("name, problem", [
    ("../../victim", "path separator"), ("a/b", "path separator"), ("a\\b", "path separator"),
    ("C:x", "path separator"), (".hidden", "starts with '.'"), ("..", "starts with '.'"),
    ("a\nb", "control character"), ("\x1b[31mred", "control character"), ("x" * 50_000_000, "more than 64"),
    ("", "empty"), (" padded", "space"), (3, "must be text"),
])
def test_bad_names_are_refused_with_file_key_and_fix(name, problem):
    with pytest.raises(InputError) as info:
        check_name(name, "b/test.toml", "key 'name'", "test name")
    message = str(info.value)
    assert message.startswith("b/test.toml, key 'name': test name ")
    assert problem in message and ". Fix: " in message
    assert "\n" not in message and "\x1b" not in message and len(message) < 400


@pytest.mark.parametrize("text, problem", [("reefed\n1", "control character"), ("x" * 200, "more than 128"),
                                           ("  ", "empty"), (None, "must be text")])
def test_bad_text_is_refused(text, problem):
    with pytest.raises(InputError, match=problem):
        check_text(text, "t.toml", "key 'phase'", "phase")
    assert check_text("full open 1/2", "t.toml", "key 'label'") == "full open 1/2"


@settings(max_examples=300, **SETTINGS)
@given(name=st.text(max_size=80))
def test_an_accepted_name_stays_one_component_inside_its_folder(tmp_path_factory, name):
    parent = tmp_path_factory.getbasetemp()
    try:
        check_name(name, "f", "key 'id'")
    except InputError as exc:
        assert all(c.isprintable() for c in str(exc))
        return
    child = inside(parent, name)
    assert child.parent == parent and child.name == name


@settings(max_examples=300, **SETTINGS)
@given(value=st.text(max_size=200) | st.integers() | st.none())
def test_shown_is_printable_and_short(value):
    out = shown(value)
    assert out.isprintable() and len(out) <= 4 * 40 + 8


# ---------------------------------------------------------------------------
# unknown keys

@pytest.mark.parametrize("word, expected", [("weight_sigm", "weight_sigma"), ("Drogue", "drogue"),
                                            ("load_scal", "load_scale"), ("wieght", "weight"), ("zzz", None)])
def test_nearest(word, expected):
    assert nearest(word, ["weight", "weight_sigma", "drogue", "main", "load_scale", "noise_acc"]) == expected


def test_unknown_key_is_refused_with_the_nearest_valid_one():
    with pytest.raises(BundleError) as info:
        check_keys({"weight": 1, "weight_sigm": 2}, ("weight", "weight_sigma"), "t.toml", "vehicle", BundleError)
    assert str(info.value) == ("t.toml, key 'vehicle.weight_sigm': unknown key 'weight_sigm'. "
                               "Fix: did you mean 'weight_sigma'? (valid: weight, weight_sigma)")
    with pytest.raises(InputError, match=r"key 'colour': unknown key 'colour'\. Fix: remove it or use one of: a, b"):
        check_keys({"colour": 1}, ("a", "b"), "t.toml")


@settings(max_examples=200, **SETTINGS)
@given(key=st.text(string.printable + "\x1b\x00é", min_size=1, max_size=300))
def test_any_unknown_key_gives_a_printable_bounded_message(key):
    valid = ("name", "units", "phase")
    if key in valid:
        return
    with pytest.raises(InputError) as info:
        check_keys({key: 1}, valid, "t.toml")
    assert str(info.value).isprintable() and len(str(info.value)) < 700
