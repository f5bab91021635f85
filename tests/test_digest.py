"""Frozen behaviour: refinements on real photos and the room equal the record field for field.

The cases are in ``tests/digest_cases.py``; the record (``tests/data/digests.json``) holds the results of the code
before the last deliberate change of behaviour, and any change of a pose, cost, verdict or render count shows here.
After a deliberate change of behaviour, regenerate it with ``python -m tests.digest_cases --write --all-machines``
and say why in the commit. The floats differ in their last bits between machine signatures (CPU vector
extensions, numpy, Taichi: ``digest_cases.machine``), so the record holds one set per signature, compared bit for
bit; on a machine without one, every refinement's verdict must equal each record's and its pose lie within
rounding of theirs (``digest_cases.portable_difference``).
"""

from __future__ import annotations

import json

import pytest

from .conftest import shared_path
from .digest_cases import CASES, load_records, machine, portable_difference, run_case


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
    got = run_case(name)
    got = json.loads(json.dumps(got, sort_keys=True, default=repr))  # the record's JSON types
    if machine() in records:  # bit for bit
        record = records[machine()][name]
        assert got["digest"] == record["digest"], _first_difference(got, record)
        return
    # float results differ in their last bits between CPUs, and the differences can grow into other iteration
    # counts: on a machine without a record, the verdicts and (within rounding) the poses of every record
    differences = {m: portable_difference(got, r[name]) for m, r in records.items()}
    assert not any(differences.values()), differences


def test_the_recorded_machines_agree_within_the_portable_tolerance():
    """What a machine without a record checks holds between the recorded CPUs (none to compare while a change of
    behaviour has been recorded on one machine only: the others record again, ``--write`` there), and it sees a
    changed verdict or a pose moved by 0.2 % of its translation."""
    import copy

    records = load_records()
    machines = sorted(records)
    assert machines
    for name in CASES:
        for a in machines[1:]:
            assert portable_difference(records[a][name], records[machines[0]][name]) is None, (name, a)
    rec = records[machines[0]]["room"]
    flipped = copy.deepcopy(rec)
    flipped["results"][0]["accepted"] = not flipped["results"][0]["accepted"]
    assert "accepted" in portable_difference(flipped, rec)
    moved = copy.deepcopy(rec)
    moved["results"][1]["tvec"] = [v * 1.002 + 0.002 for v in moved["results"][1]["tvec"]]
    assert "pose" in portable_difference(moved, rec)
