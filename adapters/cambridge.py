"""Cambridge Landmarks ``dataset_{train,test}.txt``: 3 header lines, then ``seqN/frameXXXXX.png X Y Z W P Q R``
where X Y Z is the camera centre and W P Q R the world-to-camera quaternion (CONVENTIONS §1-2). Read as
``R = R(q)``, ``t = -R c``; written back in the same form, header kept."""

from __future__ import annotations

from .posefile import PoseFile, read_poses as _read, write_poses


def read_poses(path) -> PoseFile:
    return _read(path, "cambridge")


__all__ = ["read_poses", "write_poses"]
