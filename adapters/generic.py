"""The generic 8-column form ``name qw qx qy qz tx ty tz`` (world-to-camera, w-first)."""

from __future__ import annotations

from .posefile import PoseFile, read_poses as _read, write_poses


def read_poses(path) -> PoseFile:
    return _read(path, "generic")


__all__ = ["read_poses", "write_poses"]
