"""Where a query's intrinsics come from: one focal, a pGT file, HLoc's query list, or a COLMAP model."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from hgsloc_plugin.camera import Camera

from .dialects import read_poses
from .names import canonical_name
from .posefile import PoseFile

#: (name, image width, image height) -> Camera
IntrinsicsFn = Callable[[str, int, int], Camera]


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


def _scaled_to(cam: Camera, w: int, h: int) -> Camera:
    if (cam.width, cam.height) == (w, h):
        return cam
    sx, sy = w / cam.width, h / cam.height
    return Camera(w, h, cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy)


def _lookup(table: dict[str, Camera], source, what: str) -> IntrinsicsFn:
    def get(name, w, h):
        cam = table.get(canonical_name(name))
        if cam is None:
            raise KeyError(f"{source}: {what} {name!r} not found")
        return _scaled_to(cam, w, h)

    return get


def from_cameras_json(path) -> IntrinsicsFn:
    """Intrinsics from a 3DGS trainer's ``cameras.json`` (fx, fy, size per image)."""
    from .trainer import cameras_json_intrinsics

    return cameras_json_intrinsics(path)


def from_query_list(path, *, allow_distortion: bool = False) -> IntrinsicsFn:
    """Cameras from HLoc's query list (or a NeRF ``transforms.json``, or a trainer's ``cameras.json``), rescaled to
    the image's actual size."""
    from .nerf import is_transforms_json, transforms_cameras

    if is_transforms_json(path):
        return _lookup(transforms_cameras(path, allow_distortion=allow_distortion), path, "frame")
    if str(path).lower().endswith(".json"):
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
