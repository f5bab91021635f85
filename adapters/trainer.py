"""A 3DGS trainer's ``cameras.json`` as a pose and intrinsics source (the folder itself: ``scene.resolve_scene``).

``cameras.json`` is a list of ``{"id", "img_name", "width", "height", "position": [3], "rotation": [3][3],
"fx", "fy"}``: ``position`` is the camera centre and ``rotation`` the camera-to-world rotation (OpenCV axes),
so world-to-camera is ``R = rotation^T, t = -R position``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hgsloc_plugin.core.camera import Camera
from hgsloc_plugin.core.pose import Pose, rotmat_to_qvec

from .posefile import PoseFile, Record


def _entries(path: Path) -> list[dict]:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # -sig: a BOM is no JSON error
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a list of cameras (the trainer's cameras.json)")
    for k, e in enumerate(data):
        for key in ("img_name", "width", "height", "position", "rotation", "fx", "fy"):
            if not isinstance(e, dict) or key not in e:
                raise ValueError(f"{path}: camera {k}: missing field {key!r}")
    return data


def _image_name(e: dict) -> str:
    name = str(e["img_name"])
    return name if Path(name).suffix else name + ".png"


def is_cameras_json(path) -> bool:
    return Path(path).suffix.lower() == ".json"


def read_cameras_json(path) -> PoseFile:
    """The trainer's cameras as a pose file (world-to-camera, generic dialect for writing back)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: cameras file not found")
    records, lines = [], []
    for k, e in enumerate(_entries(path)):
        Rc2w = np.asarray(e["rotation"], np.float64)
        c = np.asarray(e["position"], np.float64)
        if Rc2w.shape != (3, 3) or c.shape != (3,):
            raise ValueError(f"{path}: camera {k} ({e['img_name']}): rotation must be 3x3 and position 3 values")
        R = Rc2w.T
        pose = Pose(rotmat_to_qvec(R), -R @ c)
        name = _image_name(e)
        tokens = [name] + [repr(float(v)) for v in pose.as_array()]
        lines.append(" ".join(tokens))
        records.append(Record(len(lines), lines[-1], name, pose, tokens))
    return PoseFile(path, "generic", lines, records, True)


def cameras_json_intrinsics(path):
    """(name, width, height) -> Camera from the trainer's fx, fy and size (centred principal point), scaled to
    the image's size."""
    table = {}
    for e in _entries(Path(path)):
        table[_image_name(e)] = (int(e["width"]), int(e["height"]), float(e["fx"]), float(e["fy"]))

    def get(name, w, h):
        key = name if name in table else Path(name).name
        if key not in table:
            raise KeyError(f"{path}: no camera for {name}")
        W, H, fx, fy = table[key]
        sx, sy = w / W, h / H
        return Camera(w, h, fx * sx, fy * sy, w / 2.0, h / 2.0)

    return get
