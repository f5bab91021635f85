"""Where a query's intrinsics come from: one focal, a pGT file, HLoc's query list, a camera JSON, or a COLMAP model.

A camera given for another image size than the photo's is scaled to the photo (said once per source). A camera with
distortion is kept with it (``Camera.distortion``): the refiner undistorts the photo; ``allow_distortion`` drops
the coefficients (the photos are already undistorted).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

from hgsloc_plugin.core.camera import COLMAP_PARAMS, Camera

from .dialects import read_poses
from .names import canonical_name
from .posefile import PoseFile

logger = logging.getLogger("hgsloc_plugin")

#: (name, image width, image height) -> Camera
IntrinsicsFn = Callable[[str, int, int], Camera]
#: the fields of a plain camera JSON (``../shared/data/snow/camera.json``): one camera for every query
CAMERA_JSON_FIELDS = ("width", "height", "fx", "fy", "cx", "cy")


def from_focal(focal: float) -> IntrinsicsFn:
    """One focal length, principal point at the image centre (ACE / 7-Scenes style)."""
    if not focal > 0:
        raise ValueError(f"focal length must be positive, got {focal}")
    return lambda name, w, h: Camera.from_focal(w, h, focal)


def pgt_focals(pf: PoseFile) -> dict[str, float]:
    """name -> focal length in pixels: the 9th column of a pseudo-ground-truth file."""
    return {r.name: float(r.tokens[8]) for r in pf.records}


def from_pgt(path) -> IntrinsicsFn:
    """Per-image focal from a pseudo-ground-truth file's 9th column, centred principal point."""
    table = {canonical_name(k): v for k, v in pgt_focals(read_poses(path, "pgt")).items()}

    def get(name, w, h):
        f = table.get(canonical_name(name))
        if f is None:
            raise KeyError(f"{path}: no focal for query {name!r}")
        return Camera.from_focal(w, h, f)

    return get


def parse_query_list(path, *, allow_distortion: bool = False) -> dict[str, Camera]:
    """HLoc ``queries_with_intrinsics.txt``: ``name MODEL width height params...`` (COLMAP order)."""
    path = Path(path)
    out = {}
    for i, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1):  # -sig: a BOM is no name
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        if len(tok) < 5:
            raise ValueError(f"{path}:{i}: expected 'name MODEL width height params...', got {len(tok)} tokens")
        if tok[1].upper() not in COLMAP_PARAMS:
            raise ValueError(f"{path}:{i}: {tok[1]!r} is not a COLMAP camera model (expected 'name MODEL width "
                             "height params...', e.g. 'q.jpg SIMPLE_RADIAL 640 480 525 320 240 0'; a pose file "
                             "is no query list)")
        try:
            w, h = int(tok[2]), int(tok[3])
            params = [float(x) for x in tok[4:]]
        except ValueError as exc:
            raise ValueError(f"{path}:{i}: {exc}") from exc
        try:
            out[canonical_name(tok[0])] = Camera.from_colmap(tok[1], w, h, params, allow_distortion=allow_distortion)
        except (ValueError, IndexError) as exc:
            raise ValueError(f"{path}:{i}: {exc}") from exc
    return out


def _lookup(table: dict[str, Camera], source, what: str) -> IntrinsicsFn:
    said = []

    def get(name, w, h):
        cam = table.get(canonical_name(name))
        if cam is None:
            raise KeyError(f"{source}: {what} {name!r} not found")
        return _at_size(cam, w, h, source, said)

    return get


def _at_size(cam: Camera, w: int, h: int, source, said: list) -> Camera:
    """``cam`` scaled to the photo's ``w`` x ``h``, saying so the first time (``said`` remembers)."""
    if (cam.width, cam.height) != (w, h) and not said:
        said.append(True)
        logger.warning("%s: intrinsics given for %dx%d images, the photos are %dx%d: scaled to each photo's size",
                       source, cam.width, cam.height, w, h)
    return cam.resized(w, h)


def from_camera_json(path, data: dict | None = None, *, allow_distortion: bool = False) -> IntrinsicsFn:
    """One camera for every query from a plain JSON object: ``width height fx fy cx cy`` (pixels), and optionally
    a COLMAP ``model`` and its distortion ``params`` after those four (``{"model": "OPENCV", "params": [k1, k2,
    p1, p2]}``); scaled to each photo's size."""
    path = Path(path)
    data = data if data is not None else _read_json(path)
    missing = [k for k in CAMERA_JSON_FIELDS if k not in data]
    if missing:
        raise ValueError(f"{path}: a camera JSON needs {', '.join(CAMERA_JSON_FIELDS)}; missing {', '.join(missing)}")
    try:
        w, h = int(data["width"]), int(data["height"])
        k = [float(data[key]) for key in ("fx", "fy", "cx", "cy")]
        model = str(data.get("model", "PINHOLE")).upper()
        coeffs = [float(x) for x in data.get("params", [])]
        if model == "PINHOLE" or not coeffs:
            cam = Camera(w, h, *k)
        else:
            single = COLMAP_PARAMS.get(model, "").startswith("f ")
            cam = Camera.from_colmap(model, w, h, ([k[0], k[2], k[3]] if single else k) + coeffs,
                                     allow_distortion=allow_distortion)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from exc
    said: list = []
    return lambda name, pw, ph: _at_size(cam, pw, ph, path, said)


def _read_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8-sig"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc


def from_cameras_json(path) -> IntrinsicsFn:
    """Intrinsics from a 3DGS trainer's ``cameras.json`` (fx, fy, size per image)."""
    from .trainer import cameras_json_intrinsics

    return cameras_json_intrinsics(path)


def from_query_list(path, *, allow_distortion: bool = False) -> IntrinsicsFn:
    """Cameras from HLoc's query list, a NeRF ``transforms.json``, a trainer's ``cameras.json`` or a plain camera
    JSON (``from_camera_json``), rescaled to the image's actual size."""
    from .nerf import is_transforms_json, transforms_cameras

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: intrinsics file not found")
    if is_transforms_json(path):
        return _lookup(transforms_cameras(path, allow_distortion=allow_distortion), path, "frame")
    if path.suffix.lower() == ".json":
        data = _read_json(path)
        if isinstance(data, dict) and "width" in data:
            return from_camera_json(path, data, allow_distortion=allow_distortion)
        return from_cameras_json(path)
    return _lookup(parse_query_list(path, allow_distortion=allow_distortion), path, "query")


def from_colmap(model_dir, *, allow_distortion: bool = False) -> IntrinsicsFn:
    """Cameras of a COLMAP model (read with pycolmap), looked up by image name."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model_dir))
    table = {canonical_name(img.name): Camera.from_pycolmap(rec.cameras[img.camera_id],
                                                            allow_distortion=allow_distortion)
             for img in rec.images.values()}
    return _lookup(table, model_dir, "image")
