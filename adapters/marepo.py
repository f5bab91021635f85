"""Marepo pose files: 8 columns ``name qw qx qy qz tx ty tz``, possibly with error tensors spilled over
extra lines by ``test_marepo.py``; a line is a record iff token 0 is an image name and tokens 1-7 are finite
numbers. Other lines are kept verbatim on write."""

from __future__ import annotations

from .posefile import PoseFile, read_poses as _read, write_poses


def read_poses(path) -> PoseFile:
    return _read(path, "marepo")


__all__ = ["read_poses", "write_poses"]
