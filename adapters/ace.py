"""ACE / GLACE pose files: 11 columns ``name qw qx qy qz tx ty tz rot_err_deg tr_err_m inlier_count``.

Names are basenames (``seq-01-frame-000000.color.png``), lines in sorted test-set order. The error columns are
copied through unchanged on write (they then describe the input pose).
"""

from __future__ import annotations

from .posefile import PoseFile, read_poses as _read, write_poses


def read_poses(path) -> PoseFile:
    return _read(path, "ace")


__all__ = ["read_poses", "write_poses"]
