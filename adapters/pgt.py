"""Pseudo-ground-truth files (``rgb_file qw qx qy qz tx ty tz f``) and their per-image focal lengths."""

from __future__ import annotations

from .posefile import PoseFile, read_poses as _read, write_poses


def read_poses(path) -> PoseFile:
    return _read(path, "pgt")


def focals(pf: PoseFile) -> dict[str, float]:
    """name -> focal length in pixels (the 9th column)."""
    return {r.name: float(r.tokens[8]) for r in pf.records}


__all__ = ["focals", "read_poses", "write_poses"]
