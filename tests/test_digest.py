"""Frozen behaviour: refinements on real photos and the room equal the record field for field.

The cases are in ``tests/digest_cases.py``; the record (``tests/data/digests.json``) holds the results of the code
before the last deliberate change of behaviour, and any change of a pose, cost, verdict or render count shows here.
After a deliberate change of behaviour, regenerate it with ``python -m tests.digest_cases --write --all-machines``
and say why in the commit. The floats differ in their last bits between machine signatures (CPU vector
extensions, numpy, Taichi: ``digest_cases.machine``), so the record holds one set per signature; on a machine
without one the test is skipped.
"""

from __future__ import annotations

import json

import pytest

from .conftest import shared_path
from .digest_cases import CASES, load_records, machine, run_case


def _first_difference(a, b, path="") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted((set(a) | set(b)) - {"digest"}):
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
    records = load_records()
    if machine() not in records:  # float results differ in the last bits between CPUs
        pytest.skip(f"no record for this machine ({machine()}; recorded: {sorted(records)}): record it here with "
                    "`python -m tests.digest_cases --write` before the change to check")
    record = records[machine()][name]
    got = run_case(name)
    got = json.loads(json.dumps(got, sort_keys=True, default=repr))  # the record's JSON types
    assert got["digest"] == record["digest"], _first_difference(got, record)
