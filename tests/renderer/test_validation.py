"""camio.checks: file-level checks shared by every reader (one line naming the file, never a traceback)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from camio.checks import (FLOAT32_MAX, MAX_JSON_DEPTH, check_tree, describe, is_finite_number, json_depth,
                                 number, read_json)


class Bad(ValueError):
    pass


def _write(tmp_path, data: bytes):
    p = tmp_path / "f.json"
    p.write_bytes(data)
    return str(p)


@pytest.mark.parametrize("data,expected", [
    ('{"a": 1}'.encode("utf-16"), "not UTF-8 text (looks like UTF-16 or UTF-32)"),
    ('{"a": 1}'.encode("utf-32"), "not UTF-8 text (looks like UTF-16 or UTF-32)"),
    ('{"a": "caf\xe9"}'.encode("latin-1"), "not UTF-8 text (byte 0xe9 at offset 10)"),
    ('{"a": 1}'.encode("utf-16-le"), "not UTF-8 text (looks like UTF-16 or UTF-32)"),
    ('{"a": 1}'.encode("utf-32-be"), "not UTF-8 text (looks like UTF-16 or UTF-32)"),
    # issue 33 §4: binary junk was called UTF-16 (a NUL in its first two bytes)
    (bytes(range(256)) * 4, "binary data, not a text file"),
    (b"\x00\x01\x02\x03abc", "binary data, not a text file"),
    (bytes(np.random.default_rng(0).integers(1, 256, 300, dtype=np.uint8)), "binary data, not a text file"),
    (b"\x89PNG\r\n\x1a\n" + bytes(20), "is an image, not a JSON file"),
    (b'{"a": 1,}', "f.json:1:9: not valid JSON"),
    (b"", "f.json:1:1: not valid JSON"),
    (b"[" * 100 + b"]" * 100, f"nested 100 levels deep; at most {MAX_JSON_DEPTH}"),
    (b"[" * 200000, "nested 200000 levels deep"),
    (b"1" * 5000, "not valid JSON (Exceeds the limit"),
])
def test_read_json_refuses_with_one_line_naming_the_file(tmp_path, data, expected):
    path = _write(tmp_path, data)
    with pytest.raises(Bad) as e:
        read_json(path, Bad)
    msg = str(e.value)
    assert msg.startswith(path) and expected in msg and "\n" not in msg, msg


def test_read_json_accepts_a_utf8_bom_and_a_folder_is_named(tmp_path):
    assert read_json(_write(tmp_path, b"\xef\xbb\xbf" + json.dumps({"a": [1]}).encode()), Bad) == {"a": [1]}
    with pytest.raises(Bad, match="is a folder"):
        read_json(str(tmp_path), Bad)


def test_depth_ignores_brackets_inside_strings():
    assert json_depth('{"a": "[[[[{{{{", "b": [[1]]}') == 3, "strings do not count"
    assert json_depth(r'["\"[[[", [2]]') == 2, "escaped quotes stay inside the string"


@pytest.mark.parametrize("value,ok", [(1, True), (-2.5, True), (10**308, True), (10**309, False), (float("nan"), False),
                                      (float("inf"), False), (True, False), ("1", False), (None, False)])
def test_is_finite_number(value, ok):
    assert is_finite_number(value) is ok, f"{value!r}"


@pytest.mark.parametrize("value,kw,expected", [
    (10**400, {}, "expected a finite number, got a 401-digit integer"),
    (1e39, {"float32": True}, "expected a magnitude below 3.4e+38"),
    (1e-40, {"float32": True}, "flush to zero in float32"),
    (0.0, {"positive": True}, "expected a positive number, got 0.0"),
    (2.5, {"integer": True}, "expected an integer, got 2.5"),
    (70, {"integer": True, "high": 64}, "expected an integer <= 64, got 70"),
])
def test_number_names_the_field_and_the_problem(value, kw, expected):
    with pytest.raises(Bad) as e:
        number("s.json: image.width", value, Bad, **kw)
    assert str(e.value).startswith("s.json: image.width: ") and expected in str(e.value), str(e.value)


def test_number_passes_good_values_through():
    assert number("w", 3, Bad, integer=True, positive=True) == 3
    assert number("w", -FLOAT32_MAX, Bad, float32=True) == -FLOAT32_MAX
    assert number("w", 0.0, Bad, float32=True) == 0.0


def test_check_tree_names_the_path_of_the_bad_number():
    with pytest.raises(Bad, match=r"^s.json: objects\[1\].shape.center\[2\]: expected a finite number, got nan$"):
        check_tree({"objects": [{}, {"shape": {"center": [0, 0, float("nan")]}}]}, "s.json", Bad)
    with pytest.raises(Bad, match=r"lights\[0\].intensity\[0\]: expected a magnitude below"):
        check_tree({"lights": [{"intensity": [1e39, 0, 0]}]}, "s.json", Bad, float32=True)
    deep: list = []
    node = deep
    for _ in range(MAX_JSON_DEPTH + 5):
        node.append([])
        node = node[0]
    with pytest.raises(Bad, match="nested deeper than"):
        check_tree({"a": deep}, "s.json", Bad)


def test_describe_is_short():
    assert describe(10**50) == "a 51-digit integer"
    assert len(describe(list(range(1000)))) <= 80
