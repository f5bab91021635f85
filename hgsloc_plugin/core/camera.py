"""Camera intrinsics: a pinhole camera, and the lens distortion a query photo may carry (COLMAP's models)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

DISTORTED_MODELS = {"SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE",
              "RADIAL_FISHEYE", "THIN_PRISM_FISHEYE", "FOV"}
#: COLMAP's parameters of each model, in its order (``colmap/src/colmap/sensor/models.h``)
COLMAP_PARAMS = {"SIMPLE_PINHOLE": "f cx cy", "PINHOLE": "fx fy cx cy", "SIMPLE_RADIAL": "f cx cy k",
           "RADIAL": "f cx cy k1 k2", "OPENCV": "fx fy cx cy k1 k2 p1 p2",
           "FULL_OPENCV": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6", "OPENCV_FISHEYE": "fx fy cx cy k1 k2 k3 k4",
           "SIMPLE_RADIAL_FISHEYE": "f cx cy k", "RADIAL_FISHEYE": "f cx cy k1 k2",
           "THIN_PRISM_FISHEYE": "fx fy cx cy k1 k2 p1 p2 k3 k4 sx1 sy1", "FOV": "fx fy cx cy omega"}


@dataclass(frozen=True)
class Distortion:
    """A lens's distortion in COLMAP's terms: the camera model's name (``OPENCV``, ``SIMPLE_RADIAL``, ...) and its
    parameters after the focal lengths and principal point (``k1 k2 p1 p2`` for OPENCV), in COLMAP's order."""

    model: str
    coeffs: tuple[float, ...]

    def __str__(self) -> str:
        names = COLMAP_PARAMS[self.model].split()[-len(self.coeffs):] if self.coeffs else []
        return f"{self.model} " + " ".join(f"{n}={v:g}" for n, v in zip(names, self.coeffs))


@dataclass(frozen=True)
class Camera:
    """A camera: image size in pixels, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] and, for a photo taken through a
    lens with distortion, that distortion (``None``: a pinhole camera, what 3DGS renders).

    Convention: OpenCV axes (x right, y down, z forward); the centre of pixel (row i, col j) is (j + 0.5, i + 0.5).
    A camera with distortion describes a photo, never a rendering: the refiner undistorts such a photo to a pinhole
    camera first (``image.undistort``), and the renderer refuses it.

    ``downsample`` (>= 1): the camera of an image reduced from a finer one by this factor per axis (the query's
    pyramid): renders average as that reduction does (``RasterConfig.widening``). 1 (the default, and what
    :meth:`resized` returns): renders as 3DGS renders at its training size.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: Distortion | None = None
    downsample: float = dataclasses.field(default=1.0, repr=False)  # repr as before: resume keys stay the same

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            if int(v) != v or v <= 0:
                raise ValueError(f"Camera.{name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"Camera.{name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        d = float(self.downsample)
        if not (math.isfinite(d) and d >= 1.0):
            raise ValueError(f"Camera.downsample must be a finite number >= 1, got {self.downsample!r}")
        object.__setattr__(self, "downsample", d)

    @classmethod
    def from_focal(cls, width: int, height: int, focal: float) -> Camera:
        """One focal length, principal point at the image centre (ACE / 7-Scenes style)."""
        return cls(width, height, focal, focal, width / 2.0, height / 2.0)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_x_deg: float) -> Camera:
        """Square pixels with the given horizontal field of view, centred principal point."""
        f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return cls.from_focal(width, height, f)

    @classmethod
    def from_colmap(cls, model: str, width: int, height: int, params, *, allow_distortion: bool = False) -> Camera:
        """Build from a COLMAP model name and parameter list (COLMAP parameter order).

        PINHOLE and SIMPLE_PINHOLE are exact. A model with distortion gives a camera carrying it
        (:class:`Distortion`; the refiner undistorts the photo), or a pinhole camera when every coefficient is 0
        (how hloc writes a pinhole-like SIMPLE_RADIAL). ``allow_distortion`` states that the photos are already
        undistorted: the coefficients are then dropped and the pinhole part kept.
        """
        model = str(model).upper()
        p = [float(x) for x in params]
        if model in COLMAP_PARAMS and len(p) != len(COLMAP_PARAMS[model].split()):
            raise ValueError(f"camera model {model} takes {len(COLMAP_PARAMS[model].split())} parameters "
                             f"({COLMAP_PARAMS[model]}), got {len(p)}")
        if model == "SIMPLE_PINHOLE":
            return cls(width, height, p[0], p[0], p[1], p[2])
        if model == "PINHOLE":
            return cls(width, height, p[0], p[1], p[2], p[3])
        if model in DISTORTED_MODELS:
            single = COLMAP_PARAMS[model].startswith("f ")
            fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if single else p[:4]
            coeffs = tuple(p[3:] if single else p[4:])
            if allow_distortion or not any(coeffs):
                return cls(width, height, fx, fy, cx, cy)
            return cls(width, height, fx, fy, cx, cy, Distortion(model, coeffs))
        raise ValueError(f"unsupported camera model {model!r}")

    def colmap_params(self) -> tuple[str, list[float]]:
        """(COLMAP model name, parameters in COLMAP's order): PINHOLE for a pinhole camera, else the model of its
        distortion (the inverse of :meth:`from_colmap`)."""
        if self.distortion is None:
            return "PINHOLE", [self.fx, self.fy, self.cx, self.cy]
        model = self.distortion.model
        if COLMAP_PARAMS[model].startswith("f "):
            if self.fx != self.fy:
                raise ValueError(f"camera model {model} has one focal length, got fx={self.fx}, fy={self.fy}")
            return model, [self.fx, self.cx, self.cy, *self.distortion.coeffs]
        return model, [self.fx, self.fy, self.cx, self.cy, *self.distortion.coeffs]

    @property
    def pinhole(self) -> Camera:
        """This camera without its distortion (the same K and size)."""
        return self if self.distortion is None else dataclasses.replace(self, distortion=None)

    @classmethod
    def from_pycolmap(cls, cam, *, allow_distortion: bool = False) -> Camera:
        """Build from a ``pycolmap.Camera``; see :meth:`from_colmap` for distortion."""
        model = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
        return cls.from_colmap(model, cam.width, cam.height, list(cam.params), allow_distortion=allow_distortion)

    def scaled(self, s: float) -> Camera:
        """The camera for an image resized by s (exact under the +0.5 pixel-centre convention; a distortion, a
        function of normalised coordinates, is kept)."""
        w = max(1, int(round(self.width * s)))
        h = max(1, int(round(self.height * s)))
        return self.resized(w, h)

    def resized(self, width: int, height: int) -> Camera:
        """The camera for this image resized to ``width`` x ``height`` (each axis scaled by its own factor)."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        return Camera(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.distortion)

    def with_max_side(self, max_side: int) -> Camera:
        """This camera scaled down so that its longer side is at most ``max_side`` (never scaled up)."""
        s = min(1.0, max_side / max(self.width, self.height))
        return self if s >= 1.0 else self.scaled(s)

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix [3, 3], float64."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def __str__(self) -> str:
        text = f"{self.width}x{self.height} f=({self.fx:.3f},{self.fy:.3f}) c=({self.cx:.3f},{self.cy:.3f})"
        return text if self.distortion is None else f"{text} {self.distortion}"


def pose_cameras(camera: Camera | Sequence[Camera], n: int) -> list[Camera]:
    """A camera per pose of ``n`` from one camera or a sequence of ``n`` (intrinsics may differ, not the image
    size: a launch renders one size)."""
    if isinstance(camera, Camera):
        require_pinhole(camera)
        return [camera] * n
    cams = list(camera)
    for c in cams:
        require_pinhole(c)
    if len(cams) != n:
        raise ValueError(f"{len(cams)} cameras for {n} poses: give one camera, or one per pose")
    if len({(c.width, c.height) for c in cams}) > 1:
        raise ValueError(f"the cameras of one call must share one image size, got "
                         f"{sorted({(c.width, c.height) for c in cams})}")
    return cams


def require_pinhole(camera: Camera) -> None:
    """A ValueError when ``camera`` carries distortion: a 3DGS rendering is a pinhole image."""
    if camera.distortion is not None:
        raise ValueError(f"camera {camera} has lens distortion; 3DGS renders pinhole images: undistort the photo "
                         "first (hgsloc_plugin.core.image.undistort) and use the camera it returns")


def size_camera(camera: Camera | Sequence[Camera]) -> Camera | None:
    """The camera giving a call's image size: ``camera``, or the first of one per pose (None: no pose)."""
    return camera if isinstance(camera, Camera) else next(iter(camera), None)
