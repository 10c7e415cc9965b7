"""JsonShape counts what a JSON parse would build, from raw bytes fed in any pieces."""

from __future__ import annotations

import json
import random
from typing import Any

import pytest

from api import json_shape
from api.json_shape import JsonShape


def reference(value: Any, depth: int = 1) -> tuple[int, int, int]:
    """(values incl. keys, plus one per empty container; containers; deepest nesting)."""
    if isinstance(value, dict | list):
        items = list(value.values()) if isinstance(value, dict) else value
        count, containers, deepest = 1 + (not items) + (len(value) if isinstance(value, dict)
                                                        else 0), 1, depth
        for item in items:
            v, c, d = reference(item, depth + 1)
            count, containers, deepest = count + v, containers + c, max(deepest, d)
        return count, containers, deepest
    return 1, 0, depth - 1


def objects_and_strings(value: Any) -> tuple[int, int]:
    """(objects, strings with keys) in a parsed document."""
    if isinstance(value, dict):
        counts = [objects_and_strings(v) for v in value.values()]
        return 1 + sum(o for o, _ in counts), len(value) + sum(n for _, n in counts)
    if isinstance(value, list):
        counts = [objects_and_strings(v) for v in value]
        return sum(o for o, _ in counts), sum(n for _, n in counts)
    return 0, int(isinstance(value, str))


# strings that confuse a naive scan: brackets, separators, escaped quotes and backslashes
TRICKY = ['a"b\\', "\\", '[{,:}]\\"', '\\\\"', "é😀", "", "]]]]", '\\"[[[', "\\\\\\"]


def random_document(rng: random.Random, depth: int = 0) -> Any:
    roll = rng.random()
    if depth > 5 or roll < 0.3:
        return rng.choice([0, 1.5, -2e10, True, None, *TRICKY])
    if roll < 0.65:
        return [random_document(rng, depth + 1) for _ in range(rng.randint(0, 5))]
    return {rng.choice(["k", '"', "[", "x,y", ":", "\\"]) + str(i):
            random_document(rng, depth + 1) for i in range(rng.randint(0, 5))}


def shape_of(data: bytes, rng: random.Random, longest_piece: int) -> JsonShape:
    shape = JsonShape()
    at = 0
    while at < len(data):
        step = rng.randint(1, longest_piece)
        shape.feed(data[at:at + step])
        at += step
    return shape


@pytest.mark.parametrize("slice_bytes", [3, 7, json_shape.SLICE_BYTES])
def test_counts_match_the_parsed_document(slice_bytes: int,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Any piece sizes and vector slice sizes (so backslash runs and strings span both)."""
    monkeypatch.setattr(json_shape, "SLICE_BYTES", slice_bytes)
    rng = random.Random(slice_bytes)
    for _ in range(300):
        doc = random_document(rng)
        data = json.dumps(doc, ensure_ascii=rng.random() < 0.5,
                          indent=rng.choice([None, 1])).encode()
        shape = shape_of(data, rng, rng.choice([1, 5, 64]))
        assert (shape.values, shape.containers, shape.max_depth) == reference(doc), data
        assert (shape.objects, shape.strings) == objects_and_strings(doc), data
        assert shape.depth == 0 and shape.size == len(data) and not shape.has_nul


def test_brackets_and_separators_inside_strings_do_not_count() -> None:
    shape = JsonShape()
    shape.feed(json.dumps({"note": "[{" * 5000 + ',:"\\' * 100}).encode())
    assert (shape.values, shape.containers, shape.max_depth) == (3, 1, 1)


def test_amplifying_shapes_are_counted_without_building_them() -> None:
    n = 1_000_000
    for body, values, containers, depth in [
        (b"[" + b"{}," * (n - 1) + b"{}]", 2 * n + 1, n + 1, 2),
        (b"[" * n, n + 1, n, n),
        (b"[" + b"0," * (n - 1) + b"0]", n + 1, 1, 1),
    ]:
        shape = JsonShape()
        shape.feed(body)
        assert (shape.values, shape.containers, shape.max_depth) == (values, containers, depth)


def test_a_nul_byte_is_flagged() -> None:
    shape = JsonShape()
    shape.feed("[1]".encode("utf-16-le"))
    assert shape.has_nul
