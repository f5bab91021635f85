"""NeRF-style ``transforms.json`` (instant-ngp, nerfstudio, the NeRF synthetic sets) as poses and intrinsics.

Each frame has a ``file_path`` and a camera-to-world ``transform_matrix`` [4, 4] with OpenGL camera axes (x right,
y up, z back); intrinsics are shared at the top level or per frame: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``,
``h`` (or ``camera_angle_x`` for the focal), with optional distortion ``k1 k2 k3 k4 p1 p2``. We convert to
world-to-camera with OpenCV axes (CONVENTIONS §2: negate columns y and z, then invert). Writing refined poses back
keeps the whole JSON structure; only the refined frames' ``transform_matrix`` changes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from hgsloc_plugin.core.camera import Camera
from hgsloc_plugin.core.fileio import atomic_write_bytes
from hgsloc_plugin.core.pose import Pose, rotmat_to_qvec

from .names import canonical_name
from .posefile import PoseFile, Record

DIALECT = "transforms_json"
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
_FLIP = np.diag([1.0, -1.0, -1.0])


def is_transforms_json(path) -> bool:
    """A ``.json`` whose top level is an object with a ``frames`` list."""
    path = Path(path)
    if path.suffix.lower() != ".json":
        return False
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and isinstance(data.get("frames"), list)


def _load(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not (isinstance(data, dict) and isinstance(data.get("frames"), list)):
        raise ValueError(f"{path}: expected an object with a 'frames' list (NeRF transforms.json)")
    return data


def frame_name(frame: dict) -> str:
    """A frame's image name: its ``file_path`` without a leading './'."""
    return str(frame["file_path"]).replace("\\", "/").removeprefix("./")


def c2w_gl_to_pose(m) -> Pose:
    """A camera-to-world [4, 4] (or [3, 4]) with OpenGL axes -> world-to-camera Pose with OpenCV axes."""
    m = np.asarray(m, np.float64)
    R = m[:3, :3] @ _FLIP  # OpenGL -> OpenCV camera axes: negate the y and z columns
    U, _, Vt = np.linalg.svd(R)  # exported matrices carry rounding: the nearest rotation
    R = U @ Vt
    return Pose(rotmat_to_qvec(R.T), -R.T @ m[:3, 3])


def pose_to_c2w_gl(pose: Pose) -> list[list[float]]:
    """The inverse of :func:`c2w_gl_to_pose`: a camera-to-world [4, 4] with OpenGL axes, as nested lists."""
    m = np.eye(4)
    m[:3, :3] = pose.R.T @ _FLIP
    m[:3, 3] = pose.centre()
    return [[float(v) for v in row] for row in m]


def read_transforms_json(path) -> PoseFile:
    """The frames' poses as a ``PoseFile`` (dialect ``transforms_json``; names from ``file_path``)."""
    path = Path(path)
    records, seen = [], {}
    for k, fr in enumerate(_load(path)["frames"]):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise ValueError(f"{path}: frame {k}: needs 'file_path' and 'transform_matrix'")
        name = frame_name(fr)
        m = np.asarray(fr["transform_matrix"], np.float64)
        if m.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"{path}: frame {k} ({name}): transform_matrix must be 4x4, got {list(m.shape)}")
        if name in seen:
            raise ValueError(f"{path}: frame {k}: image {name!r} appears twice (first: frame {seen[name]})")
        seen[name] = k
        pose = c2w_gl_to_pose(m) if np.all(np.isfinite(m)) else None
        records.append(Record(k + 1, "", name, pose, [name]))
    if not records:
        raise ValueError(f"{path}: no frames")
    return PoseFile(path, DIALECT, [], records)


def write_transforms_json(path, poses, like: PoseFile) -> Path:
    """``like``'s JSON with the frames in ``poses`` given new ``transform_matrix`` values; all else unchanged."""
    path = Path(path)
    if path.exists() and path.resolve() == like.path.resolve():
        raise ValueError(f"{path}: refusing to overwrite the input pose file")
    data = _load(like.path)
    for fr in data["frames"]:
        p = poses.get(frame_name(fr))
        if p is not None and p != like[frame_name(fr)]:
            fr["transform_matrix"] = pose_to_c2w_gl(p)
    atomic_write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())
    return path


def transforms_cameras(path, *, allow_distortion: bool = False) -> dict[str, Camera]:
    """canonical image name -> Camera at the size the file gives (``w``, ``h``), from its shared or per-frame
    intrinsics. Distortion coefficients become the camera's :class:`~hgsloc_plugin.core.camera.Distortion`
    (OpenCV's ``k1 k2 p1 p2``, with ``k3 k4`` FULL_OPENCV, ``is_fisheye`` OPENCV_FISHEYE's ``k1 k2 k3 k4``): the
    refiner undistorts each photo; all zero, or ``allow_distortion`` (the images are already undistorted), a pinhole
    camera. ``intrinsics.from_query_list`` scales them to each image's size."""
    path = Path(path)
    data = _load(path)
    table = {}
    for k, fr in enumerate(data["frames"]):
        v = {**{key: val for key, val in data.items() if key != "frames"}, **fr}

        def need(key, v=v, k=k):
            if key not in v:
                raise ValueError(f"{path}: frame {k}: no {key!r} (per frame or shared)")
            return float(v[key])

        w, h = need("w"), need("h")
        if "fl_x" in v:
            fx = float(v["fl_x"])
        elif "camera_angle_x" in v:
            fx = 0.5 * w / math.tan(0.5 * float(v["camera_angle_x"]))
        else:
            raise ValueError(f"{path}: frame {k}: no 'fl_x' or 'camera_angle_x' (per frame or shared)")
        fy = float(v.get("fl_y", fx))
        c = {d: float(v.get(d, 0.0)) for d in DISTORTION}
        if v.get("is_fisheye"):
            model, coeffs = "OPENCV_FISHEYE", [c["k1"], c["k2"], c["k3"], c["k4"]]
        elif c["k3"] or c["k4"]:
            model, coeffs = "FULL_OPENCV", [c["k1"], c["k2"], c["p1"], c["p2"], c["k3"], c["k4"], 0.0, 0.0]
        else:
            model, coeffs = "OPENCV", [c["k1"], c["k2"], c["p1"], c["p2"]]
        table[canonical_name(frame_name(fr))] = Camera.from_colmap(
            model, int(round(w)), int(round(h)), [fx, fy, float(v.get("cx", w / 2)), float(v.get("cy", h / 2)),
                                                  *coeffs], allow_distortion=allow_distortion)
    return table
