"""Images: loading queries from any supported form, deterministic resizing, size checks ([H, W, 3] float32).

No torch here: importing it costs a new process about 2.5 s (of 3.8 s for the whole package), and a refinement
needs none of it. A torch tensor given as a query is recognised without importing torch.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
from PIL import Image

from .camera import Camera


def load_image(image, *, name: str = "image", background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Any supported query image as float32 [H, W, 3] in [0, 1].

    Accepts a path (PNG/JPEG; RGBA is composited on ``background``, the map's, unless fully opaque), a numpy array
    [H, W, C] or a torch tensor [C, H, W] (uint8, or float in [0, 1]) with C = 3, 1 or 4 (grey is repeated, RGBA
    composited on ``background`` as for a file; a 2-D array or tensor [H, W] is grey).
    """
    if isinstance(image, (str, Path)):
        p = Path(image)
        if not p.is_file():
            raise FileNotFoundError(f"{p}: query image not found")
        with Image.open(p) as im:
            im = im.convert("RGBA") if im.mode in ("RGBA", "LA", "P") else im.convert("RGB")
            a = np.asarray(im, dtype=np.float32) / 255.0
        return _to_rgb(a, background)
    torch = sys.modules.get("torch")  # a tensor exists only when the caller imported torch
    if torch is not None and isinstance(image, torch.Tensor):
        t = image.detach().cpu()
        t = t[None] if t.ndim == 2 else t
        if t.ndim != 3 or t.shape[0] not in (1, 3, 4):
            raise ValueError(f"{name}: a torch image must be [3, H, W] (or [1 | 4, H, W], [H, W]), "
                             f"got {tuple(image.shape)}")
        t = t if t.dtype == torch.uint8 else t.float()  # uint8 stays 0-255; numpy has no bfloat16
        a = t.permute(1, 2, 0).numpy()
    else:
        a = np.asarray(image)
        a = a[..., None] if a.ndim == 2 else a
        if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
            raise ValueError(f"{name}: a numpy image must be [H, W, 3] (or [H, W, 1 | 4], [H, W]), "
                             f"got {np.asarray(image).shape}")
    if a.dtype == np.uint8:
        return _to_rgb(np.asarray(a, dtype=np.float32) / 255.0, background)
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: image has non-finite values")
    if a.min() < -0.05 or a.max() > 1.5:  # renderings may overshoot 1 slightly; 0-255 floats are an error
        raise ValueError(f"{name}: float images must be in [0, 1] (got range {a.min():.3g}..{a.max():.3g})")
    return _to_rgb(np.clip(a, 0.0, 1.0), background)


def _to_rgb(a: np.ndarray, background) -> np.ndarray:
    """[H, W, 1 | 3 | 4] float in [0, 1] -> contiguous float32 [H, W, 3]: grey repeated, RGBA composited on
    ``background``."""
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    elif a.shape[2] == 4:
        a = a[..., :3] * a[..., 3:4] + (1.0 - a[..., 3:4]) * np.asarray(background, np.float32)
    return np.ascontiguousarray(a, dtype=np.float32)


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Antialiased bilinear resize of [H, W, 3] float32 to [height, width, 3] (a triangle filter widened by the
    reduction factor: the filter of ``torch.nn.functional.interpolate(mode="bilinear", antialias=True)``, which
    follows Pillow's; here Pillow's, per channel in 32-bit float mode); deterministic."""
    if img.shape[0] == height and img.shape[1] == width:
        return img
    planes = [np.ascontiguousarray(img[..., c], dtype=np.float32) for c in range(3)]
    # each plane as a 32-bit float image, straight from its bytes (Image.fromarray's array-interface checks skipped)
    chans = [np.asarray(Image.frombuffer("F", (img.shape[1], img.shape[0]), p, "raw", "F", 0, 1)
                        .resize((int(width), int(height)), Image.Resampling.BILINEAR)) for p in planes]
    return np.ascontiguousarray(np.stack(chans, axis=-1).clip(0, 1), dtype=np.float32)


def check_size(img: np.ndarray, camera: Camera, resize: bool, name: str = "image") -> np.ndarray:
    """The image at the camera's size, or a ValueError naming both sizes."""
    h, w = img.shape[:2]
    if (w, h) == (camera.width, camera.height):
        return img
    if not resize:
        raise ValueError(f"{name}: image is {w}x{h} but the camera is {camera.width}x{camera.height} "
                         "(set RefineConfig(resize_query=True) to resize it)")
    return resize_image(img, camera.width, camera.height)


def undistort(img: np.ndarray, camera: Camera) -> tuple[np.ndarray, Camera]:
    """A photo taken through ``camera``'s lens distortion as the pinhole camera's photo: (image [H', W', 3]
    float32, pinhole Camera of size W' x H'); a pinhole camera's photo is returned as it is.

    The pinhole camera is COLMAP's own choice for the lens (``pycolmap.undistort_camera``: the same focal
    lengths, the image size grown or cropped so that no pixel is blank), as ``colmap image_undistorter`` makes it;
    each of its pixel centres is mapped into the photo by pycolmap's camera model and sampled bilinearly (edge
    pixels repeated). ``img`` must be at ``camera``'s size."""
    if camera.distortion is None:
        return img, camera
    if img.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"image is {img.shape[1]}x{img.shape[0]} but the camera is {camera.width}x{camera.height}")
    pinhole, rows, cols = _undistortion_map(camera)
    return _bilinear(img, rows, cols), pinhole


_MAPS: dict[Camera, tuple[Camera, np.ndarray, np.ndarray]] = {}  # a few lenses' maps, shared by their queries
_MAPS_LOCK = threading.Lock()  # lockstep batches refine their queries in threads


def _undistortion_map(camera: Camera) -> tuple[Camera, np.ndarray, np.ndarray]:
    """(pinhole camera, [H', W'] rows and columns in ``camera``'s photo, float array coordinates) of its pixels."""
    with _MAPS_LOCK:
        hit = _MAPS.get(camera)
        if hit is None:
            hit = _MAPS[camera] = _make_undistortion_map(camera)
            if len(_MAPS) > 4:
                _MAPS.pop(next(iter(_MAPS)))
    return hit


def _make_undistortion_map(camera: Camera) -> tuple[Camera, np.ndarray, np.ndarray]:
    import pycolmap

    model, params = camera.colmap_params()
    src = pycolmap.Camera(model=model, width=camera.width, height=camera.height, params=params)
    if hasattr(pycolmap, "undistort_camera"):
        dst = pycolmap.undistort_camera(pycolmap.UndistortCameraOptions(), src)
    else:  # an older pycolmap: the same size and intrinsics
        dst = pycolmap.Camera(model="PINHOLE", width=camera.width, height=camera.height,
                              params=[camera.fx, camera.fy, camera.cx, camera.cy])
    pinhole = Camera.from_pycolmap(dst)
    v, u = np.mgrid[0:pinhole.height, 0:pinhole.width].astype(np.float64) + 0.5
    rays = dst.cam_from_img(np.stack([u.ravel(), v.ravel()], axis=1))  # [M, 2], normalised
    try:
        xy = src.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], axis=1), check_cheirality=False)
    except TypeError:  # pycolmap before 3.12 projects normalised 2-D points
        xy = src.img_from_cam(rays)
    xy = np.asarray(xy, np.float64).reshape(pinhole.height, pinhole.width, 2) - 0.5  # pixel centres at +0.5
    return pinhole, xy[..., 1], xy[..., 0]


def _bilinear(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``img`` [H, W, C] sampled at float (row, col) array coordinates [h, w] (bilinear, edges repeated)."""
    h, w = img.shape[:2]
    r = np.clip(rows, 0.0, h - 1.0)
    c = np.clip(cols, 0.0, w - 1.0)
    r0 = np.minimum(np.floor(r).astype(np.intp), h - 2) if h > 1 else np.zeros(r.shape, np.intp)
    c0 = np.minimum(np.floor(c).astype(np.intp), w - 2) if w > 1 else np.zeros(c.shape, np.intp)
    r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
    fr, fc = (r - r0)[..., None], (c - c0)[..., None]
    top = img[r0, c0] * (1.0 - fc) + img[r0, c1] * fc
    bottom = img[r1, c0] * (1.0 - fc) + img[r1, c1] * fc
    return np.ascontiguousarray(top * (1.0 - fr) + bottom * fr, dtype=np.float32)


_NOTICED: set[tuple[str, str]] = set()


def distortion_notice(camera: Camera, flag: str) -> None:
    """Say once per process (per lens model and flag) that photos are undistorted, naming ``flag``, the caller's
    way to declare photos already undistorted (``--allow-distortion``, ``--allow_distortion``, ...)."""
    import logging

    key = (camera.distortion.model if camera.distortion is not None else "", flag)
    if key in _NOTICED:
        return
    _NOTICED.add(key)
    logging.getLogger("hgsloc_plugin").warning(
        "undistorting the query photos (%s) to pinhole cameras before refining: the map renders pinhole images. If "
        "the photos are already undistorted, pass %s", camera.distortion, flag)
