"""Adapters: read and write the pose files of ACE, Marepo, HLoc and friends (``dialects``), intrinsics, and a
localizer's confidence.

Conversions between the localizers' conventions and ours happen here and nowhere else.
"""

from .dialects import DIALECTS, read_poses, write_poses
from .names import canonical_name, match_names, resolve_image
from .posefile import PoseFile, Record

__all__ = ["DIALECTS", "PoseFile", "Record", "canonical_name", "match_names", "read_poses", "resolve_image",
           "write_poses"]
