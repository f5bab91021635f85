"""HLoc's files: results (8 columns ``name qw qx qy qz tx ty tz``) and the query list with intrinsics.

The refinement step that runs on them is :mod:`hgsloc_plugin.hloc_step` (``python -m hgsloc_plugin.hloc_step``).
"""

from __future__ import annotations

from .dialects import read_poses as _read
from .dialects import write_poses
from .intrinsics import from_query_list, parse_query_list
from .posefile import PoseFile

__all__ = ["from_query_list", "parse_query_list", "read_poses", "write_poses"]


def read_poses(path) -> PoseFile:
    """An hloc results file (``name qw qx qy qz tx ty tz``, world-to-camera)."""
    return _read(path, "hloc")
