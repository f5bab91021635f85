"""Command-line values with units and counts, shared by every command line (``hgsloc``, the hloc step, examples).

Lengths are in scene units, written as metres ('0.25m', '25cm', '250mm' or a bare number); angles in degrees
('5deg', '5' or '0.1rad').
"""

from __future__ import annotations

import argparse
import re


def count_arg(text: str, minimum: int = 0) -> int:
    """argparse type of a count (``--limit``, ``--workers``): an integer >= ``minimum``."""
    try:
        n = int(text)
    except ValueError:
        n = None
    if n is None or n < minimum:
        raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}")
    return n


def positive_count_arg(text: str) -> int:
    """argparse type of a count that must be >= 1 (``--sample``, ``--queries``)."""
    return count_arg(text, 1)


_LENGTH_UNITS = {"": 1.0, "m": 1.0, "cm": 0.01, "mm": 0.001}
_ANGLE_UNITS = {"": 1.0, "deg": 1.0, "rad": 57.29577951308232}


def _with_unit(text: str, units: dict[str, float], flag: str, zero: bool = False) -> float:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-z]*)\s*", text)
    if not m or m.group(2) not in units:
        raise ValueError(f"{flag}: expected a positive number with an optional unit "
                         f"({', '.join(u for u in units if u)}), got {text!r}")
    v = float(m.group(1)) * units[m.group(2)]
    if not (v > 0 or (zero and v == 0)):
        raise ValueError(f"{flag}: must be > 0, got {text!r}")
    return v


def parse_length(text: str, flag: str = "--max-shift") -> float:
    """'0.25m', '25cm', '0.25' -> 0.25 (scene units, taken as metres)."""
    return _with_unit(text, _LENGTH_UNITS, flag)


def parse_pixels(text: str, flag: str = "--lod-pixels") -> float:
    """'2', '2px' -> 2.0 (pixels, > 0)."""
    return _with_unit(text, {"": 1.0, "px": 1.0}, flag)


def parse_angle(text: str, flag: str = "--max-rotation", zero: bool = False) -> float:
    """'5deg', '5', '0.1rad' -> degrees (> 0; ``zero``: 0 allowed too)."""
    return _with_unit(text, _ANGLE_UNITS, flag, zero)


def prior_error_overrides(error: str | None, rotation_error: str | None,
                          flags: tuple[str, str] = ("--prior-error", "--prior-rotation-error")) -> dict:
    """``RefineConfig`` fields from the priors' typical-error flags ('2cm', '1deg'; None: not given), for every
    command line that takes them (``hgsloc refine``, the hloc step, the examples); a bad value raises ValueError
    naming its flag (``flags``)."""
    out = {}
    if error is not None:
        out["prior_error"] = parse_length(error, flags[0])
    if rotation_error is not None:
        out["prior_error_deg"] = parse_angle(rotation_error, flags[1])
    return out


def parse_map_floor(text: str, flag: str = "--map-floor") -> dict:
    """'0.6%,0.2deg' or '0.6%,0.2deg,0.12cs' (the camera-centre floor in % of the query's median depth, the rotation
    floor in degrees and, optionally, the cs cost bound, as ``hgsloc check --measure-floor`` prints them) -> the
    ``Tuning`` fields ``map_floor_depth`` (a fraction), ``map_floor_deg`` and ``map_cost_bound``; ValueError naming
    ``flag`` otherwise. Zero floors are allowed, as ``Tuning`` allows them: views whose minima lie at their poses to
    the last bit (a map rendering the views themselves) measure a floor of 0."""
    num = r"([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)"
    m = re.fullmatch(rf"\s*{num}\s*%\s*,\s*([^,]+?)\s*(?:,\s*{num}\s*cs\s*)?", text)
    if not m:
        raise ValueError(f"{flag}: expected 'P%,Rdeg' or 'P%,Rdeg,Ccs' (e.g. '0.6%,0.2deg,0.12cs'), got {text!r}")
    out = {"map_floor_depth": float(m.group(1)) / 100.0, "map_floor_deg": parse_angle(m.group(2), flag, zero=True)}
    if m.group(3) is not None:
        if not float(m.group(3)) > 0:
            raise ValueError(f"{flag}: the cost bound must be > 0, got {text!r}")
        out["map_cost_bound"] = float(m.group(3))
    return out
