"""Frozen behaviour: refinements on real photos and the room equal the record field for field.

The cases are in ``tests/digest_cases.py``; the record (``tests/data/digests.json``) was made by the code before
the renderer / refiner restructuring, and any change of a pose, cost, verdict or render count shows here. After a
deliberate change of behaviour, regenerate it with ``python -m tests.digest_cases --write`` and say why in the
commit.
"""

from __future__ import annotations

import json

import pytest

from .conftest import shared_path
from .digest_cases import CASES, RECORD, run_case


def _first_difference(a, b, path="") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b) - {"digest"}):
            d = _first_difference(a.get(k), b.get(k), f"{path}.{k}")
            if d:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} items, recorded {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            d = _first_difference(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    same = a == b or (isinstance(a, float) and isinstance(b, float) and a != a and b != b)  # nan is nan here
    return None if same else f"{path}: {a!r}, recorded {b!r}"


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_refinements_equal_the_record(name):
    shared_path("snow", "snow_sharp.ply")
    record = json.loads(RECORD.read_text())[name]
    got = run_case(name)
    got = json.loads(json.dumps(got, sort_keys=True, default=repr))  # the record's JSON types
    assert got["digest"] == record["digest"], _first_difference(got, record)
