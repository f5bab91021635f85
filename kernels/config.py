"""Rasterizer settings shared by the kernels (the kernel-cache key)."""

from __future__ import annotations

from dataclasses import dataclass, replace

#: the variance (pixels^2 of the smaller image) of the triangle filter of an antialiased bilinear reduction
#: (``core/image.resize_image``, Pillow's, support one output pixel): its weights' variance over the input samples,
#: averaged over their phase, is 1/6 at every reduction factor above 1
RESIZE_FILTER_PX2 = 1.0 / 6.0

#: the per-pixel derivative blend's tile edge (``RasterConfig.grad_tile_size`` None): 64 pixels, one bit each in a
#: ``pose_grad.pixel_masks`` entry
PIXEL_GRAD_TILE = 8


@dataclass(frozen=True, kw_only=True)
class RasterConfig:
    """Forward-pass constants; defaults follow gsplat 1.5.3 ``rasterize_mode="classic"`` (CONVENTIONS §6).

    Attributes:
        tile_size: tile edge in pixels.
        grad_tile_size: tile edge of the lists the pose-derivative pass blends (``blend_grad.py``); None: the
            layout's (:meth:`grad_tile`): ``tile_size`` for the tile-parallel blend on the CPU, a task per tile
            whose Gaussians visit their ellipse pixels only, so that larger tiles only save list entries and row
            set-ups (``benchmarks/derivative_pass.md``); ``PIXEL_GRAD_TILE`` (8) otherwise: the per-pixel blend,
            whose pixels walk their tile's whole list, and any blend on CUDA (a tile a thread there). The same
            images and derivatives at any size, to float32 rounding.
        grad_masks: for the per-pixel derivative blend (``blend`` "pixel"): "on": each list entry carries a mask of
            the tile's pixels its Gaussian can reach (``pose_grad.pixel_masks``; needs ``grad_tile_size`` <= 8), so
            a pixel skips the others on one bit test: the same numbers, less time on the CPU; "off"; "auto" (on
            for the CPU when the tiles allow; off on CUDA, where it is not measured yet). The tile-parallel
            derivative blend visits each Gaussian's pixels only and never uses them
            (``benchmarks/derivative_pass.md``).
        eps2d: dilation added to the 2D covariance diagonal.
        alpha_max: cap on per-Gaussian alpha (gsplat 0.999, Inria 0.99).
        alpha_min: Gaussians with alpha below this are skipped (1/255).
        t_eps: blending stops before the Gaussian that would bring transmittance to <= t_eps.
        near_plane / far_plane: depth culling (camera z).
        radius_mode: "gsplat" (opacity-aware per-axis box) or "inria" (3 sigma of the largest eigenvalue, square).
        blend: "pixel" (one task per pixel, the GPU layout), "splat" (one task per tile, each Gaussian touching
            only its box: much faster on the CPU) or "auto" (splat on CPU, pixel on CUDA), for the renders and the
            derivative pass alike. Same images; the derivatives equal to float32 rounding.
        sort: "serial" (each pose's radix and tile sort on one thread: the CPU layout), "parallel" (one tile key
            per Gaussian and tile, sorted by a device radix sort: the GPU layout; ``tile_sort.bin_parallel``) or
            "auto" (serial on CPU, parallel on CUDA). Same tile lists, entry for entry.
        tile_test: which tiles a Gaussian is binned into: "ellipse" (the tiles of its box its alpha ellipse
            reaches, ``footprint.py``: shorter lists, the same images), "box" (every tile of its box, as gsplat)
            or "auto" (ellipse on CUDA, box on the CPU: ``footprint.uses_ellipse_tiles``).
        max_batch_elements: poses x Gaussians handled per launch; larger calls are split into chunks.
    """

    tile_size: int = 16
    grad_tile_size: int | None = None
    grad_masks: str = "auto"
    eps2d: float = 0.3
    alpha_max: float = 0.999
    alpha_min: float = 1.0 / 255.0
    t_eps: float = 1e-4
    near_plane: float = 0.01
    far_plane: float = 1e10
    radius_mode: str = "gsplat"
    blend: str = "auto"
    sort: str = "auto"
    tile_test: str = "auto"
    max_batch_elements: int = 8_000_000

    def __post_init__(self) -> None:
        if self.radius_mode not in ("gsplat", "inria"):
            raise ValueError(f"radius_mode must be 'gsplat' or 'inria', got {self.radius_mode!r}")
        if self.blend not in ("auto", "pixel", "splat"):
            raise ValueError(f"blend must be 'auto', 'pixel' or 'splat', got {self.blend!r}")
        if self.grad_masks not in ("auto", "on", "off"):
            raise ValueError(f"grad_masks must be 'auto', 'on' or 'off', got {self.grad_masks!r}")
        if self.grad_masks == "on" and self.grad_tile_size is not None and self.grad_tile_size > 8:
            raise ValueError(f"grad_masks='on' needs grad_tile_size <= 8 (64 pixels), got {self.grad_tile_size}")
        if self.sort not in ("auto", "serial", "parallel"):
            raise ValueError(f"sort must be 'auto', 'serial' or 'parallel', got {self.sort!r}")
        if self.tile_test not in ("auto", "ellipse", "box"):
            raise ValueError(f"tile_test must be 'auto', 'ellipse' or 'box', got {self.tile_test!r}")
        if not (0 < self.alpha_max <= 1):
            raise ValueError(f"alpha_max must be in (0, 1], got {self.alpha_max}")
        grad_tile_ok = self.grad_tile_size is None or self.grad_tile_size > 0
        if self.tile_size <= 0 or not grad_tile_ok or self.max_batch_elements <= 0:
            raise ValueError("tile_size, grad_tile_size and max_batch_elements must be positive")

    def grad_tile(self, cpu_tiles: bool) -> int:
        """The derivative pass's tile edge: ``grad_tile_size``, or when None ``tile_size`` where ``cpu_tiles`` (the
        tile-parallel blend on the CPU) and ``PIXEL_GRAD_TILE`` elsewhere."""
        if self.grad_tile_size is not None:
            return self.grad_tile_size
        return self.tile_size if cpu_tiles else PIXEL_GRAD_TILE

    def widening(self, downsample: float = 1.0) -> tuple[float, float]:
        """(dilation, filter), pixels^2 added to a projected covariance's diagonal for a camera whose image is a
        finer one's reduced ``downsample`` times per axis (``Camera.downsample``, >= 1): the dilation ``eps2d``
        of the finer pixels, ``eps2d / downsample^2`` in these, and the reduction's filter
        (``RESIZE_FILTER_PX2``, 0 at 1), which the projection adds with its opacity compensation
        (``projection.py``). At 1: ``(eps2d, 0)``, the 3DGS rendering."""
        if downsample == 1.0:
            return self.eps2d, 0.0
        return self.eps2d / (downsample * downsample), RESIZE_FILTER_PX2

    def for_layout(self, cpu_tiles: bool) -> RasterConfig:
        """This config with ``grad_tile_size`` set to :meth:`grad_tile` (what the kernels read)."""
        return replace(self, grad_tile_size=self.grad_tile(cpu_tiles))


#: The layout "auto" picks on CUDA, as ``RasterConfig`` fields: forced on any backend it runs the GPU's launch
#: structure (``benchmarks/throughput.py --layout cuda``, tests). The pickers: ``render.buffers.blend_mode`` and
#: ``sort_mode``, ``footprint.uses_ellipse_tiles``, ``pose_grad.uses_masks`` (checked in ``tests/test_tile_sort.py``).
CUDA_LAYOUT = {"blend": "pixel", "sort": "parallel", "grad_masks": "off", "tile_test": "ellipse"}
