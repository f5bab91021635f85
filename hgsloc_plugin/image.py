"""Images: loading queries from any supported form, deterministic resizing, size checks ([H, W, 3] float32).

No torch here: importing it costs a new process about 2.5 s (of 3.8 s for the whole package), and a refinement
needs none of it. A torch tensor given as a query is recognised without importing torch.
"""

from __future__ import annotations

import sys
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
