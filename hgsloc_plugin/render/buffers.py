"""Device buffers of the renderer, as typed records: per-Gaussian records, per-image-size workspaces, the pool.

Shapes use B (poses per launch), n (Gaussians), H x W (image), tx x ty (tiles). With the parallel tile sort
(``RasterConfig.sort``) the projection's depth / rect / ntiles, the tile starts and the lists are torch tensors
on the Taichi device, which the Taichi kernels read and write in place; otherwise Taichi ndarrays.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from ..backend import current_arch
from ..kernels import window_grad
from ..kernels.layout import Rec
from ..kernels.pose_grad import NDER, NXI
from ..kernels.readback import readback_kernel
from ..kernels.tile_sort import RADIX

logger = logging.getLogger("hgsloc_plugin.render")

_HOST_DTYPES = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32, ti.i64: np.int64}


def read_rows(arr, n: int) -> np.ndarray:
    """The first ``n`` rows of a device array [B, ...] (a Taichi ndarray or a torch tensor) as a host array
    [n, ...] (``kernels/readback.py``: a workspace's ``to_numpy`` copies all B poses)."""
    if not isinstance(arr, ti.Ndarray):
        if arr.is_cuda:
            ti.sync()  # Taichi kernels that wrote the tensor are done before torch copies it
        return arr[:n].to("cpu", copy=True).numpy()
    out = np.empty((n,) + tuple(arr.shape[1:]), _HOST_DTYPES[arr.dtype])
    readback_kernel()(arr, out)
    return out


def _torch_has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def sort_mode(requested: str, arch: str) -> str:
    """The tile sort a renderer uses (``RasterConfig.sort``) on backend ``arch``: "parallel" on CUDA for
    "auto", unless torch (which sorts the keys on the device) has no CUDA there: then "serial", with a warning."""
    if requested == "serial" or (requested == "auto" and arch != "cuda"):
        return "serial"
    if arch == "cuda" and not _torch_has_cuda():
        msg = ("Taichi runs on CUDA but torch has no CUDA (torch.cuda.is_available() is False), and the parallel "
               "tile sort sorts its keys with torch on the GPU")
        if requested == "parallel":
            raise RuntimeError(f"RasterConfig(sort='parallel'): {msg}; install a CUDA build of torch")
        logger.warning("%s: falling back to the serial sort (one GPU thread per pose, several times slower); "
                       "install a CUDA build of torch", msg)
        return "serial"
    return "parallel"


def torch_device() -> str:
    """The torch device beside Taichi's backend."""
    return "cuda" if current_arch() == "cuda" else "cpu"


def _torch_zeros(shape, dtype_name: str, fill: bool = True):
    import torch

    make = torch.zeros if fill else torch.empty
    return make(shape, dtype=getattr(torch, dtype_name), device=torch_device())


@dataclass
class ProjectionRecords:
    """Per-Gaussian outputs of the projection and the tile sort, [B, n, ...]; one set serves every image size.

    Attributes:
        depth [B, n]; rect [B, n, 4] (tile box); ntiles [B, n] (tiles touched; 0: culled); packed [B, n, Rec.SIZE]
        (the blend's record per Gaussian); keys_a / keys_b / ids_a / ids_b [B, n] and rects [4, B, n]: the
        serial sort's scratch (None for the parallel sort).
    """

    batch: int
    gaussians: int
    depth: object
    rect: object
    ntiles: object
    packed: ti.Ndarray
    keys_a: ti.Ndarray | None = None
    keys_b: ti.Ndarray | None = None
    ids_a: ti.Ndarray | None = None
    ids_b: ti.Ndarray | None = None
    rects: ti.Ndarray | None = None

    @classmethod
    def allocate(cls, B: int, n: int, parallel: bool) -> ProjectionRecords:
        nd = ti.ndarray
        packed = nd(ti.f32, (B, n, Rec.SIZE))
        if parallel:
            return cls(B, n, _torch_zeros((B, n), "float32"), _torch_zeros((B, n, 4), "int32"),
                       _torch_zeros((B, n), "int32"), packed)
        return cls(B, n, nd(ti.f32, (B, n)), nd(ti.i32, (B, n, 4)), nd(ti.i32, (B, n)), packed,
                   nd(ti.u32, (B, n)), nd(ti.u32, (B, n)), nd(ti.i32, (B, n)), nd(ti.i32, (B, n)),
                   nd(ti.i32, (4, B, n)))


@dataclass
class DerivativeRecords:
    """Per-Gaussian derivative records of the pose-derivative pass: dpacked [B, n, NDER]."""

    batch: int
    gaussians: int
    dpacked: ti.Ndarray

    @classmethod
    def allocate(cls, B: int, n: int) -> DerivativeRecords:
        return cls(B, n, ti.ndarray(ti.f32, (B, n, NDER)))


@dataclass
class ImageBuffers:
    """Blended images: rgb [B, H, W, 3], alpha [B, H, W], accumulated depth dimg [B, H, W]."""

    rgb: ti.Ndarray
    alpha: ti.Ndarray
    dimg: ti.Ndarray

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> ImageBuffers:
        nd = ti.ndarray
        return cls(nd(ti.f32, (B, H, W, 3)), nd(ti.f32, (B, H, W)), nd(ti.f32, (B, H, W)))


@dataclass
class WindowBuffers:
    """The windowed cost's scratch: horizontal pass [B, H, W, 3, 3], row sums [B, H, 1, 2], sums [B, 2]."""

    h: ti.Ndarray
    rows: ti.Ndarray
    out: ti.Ndarray

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> WindowBuffers:
        nd = ti.ndarray
        return cls(nd(ti.f32, (B, H, W, 3, 3)), nd(ti.f32, (B, H, 1, 2)), nd(ti.f64, (B, 2)))


@dataclass
class StatBuffers:
    """The fused pixel cost's scratch: per-run statistics [B, rows, tx, Stat.SIZE] and totals [B, Stat.SIZE]."""

    runs: ti.Ndarray
    stats: ti.Ndarray


@dataclass
class Workspace:
    """Buffers of one image size and tiling for up to ``batch`` poses: the poses and intrinsics uploaded, the tile
    lists' starts [B, tx * ty + 1] and offsets isect_base [B], the serial sort's counters (totals [B],
    hist [B, RADIX], cursor [B, tx * ty]; None for the parallel sort), and, made on first use, the blended
    images and the cost scratch."""

    batch: int
    tile: int
    tiles: tuple[int, int]
    viewmats: ti.Ndarray  # [B, 3, 4]
    campos: ti.Ndarray  # [B, 3]
    intrin: ti.Ndarray  # [4]: fx, fy, cx, cy
    extent: ti.Ndarray  # [2]: the projection's extent coefficients
    isect_base: ti.Ndarray  # [B]
    background: ti.Ndarray  # [3]
    tile_start: object
    totals: ti.Ndarray | None = None
    hist: ti.Ndarray | None = None
    cursor: ti.Ndarray | None = None
    images: ImageBuffers | None = None
    window: WindowBuffers | None = None
    stats: StatBuffers | None = None

    @classmethod
    def allocate(cls, B: int, width: int, height: int, tile: int, parallel: bool) -> Workspace:
        tx, ty = -(-width // tile), -(-height // tile)
        if max(tx, ty) >= 1 << 15:  # the sort packs tile ranges in 16 bits
            raise ValueError(f"image {width}x{height} has too many tiles per axis")
        nd = ti.ndarray
        common = dict(batch=B, tile=tile, tiles=(tx, ty), viewmats=nd(ti.f32, (B, 3, 4)), campos=nd(ti.f32, (B, 3)),
                      intrin=nd(ti.f32, (4,)), extent=nd(ti.f32, (2,)), isect_base=nd(ti.i64, (B,)),
                      background=nd(ti.f32, (3,)))
        if parallel:
            return cls(**common, tile_start=_torch_zeros((B, tx * ty + 1), "int32"))
        return cls(**common, tile_start=nd(ti.i32, (B, tx * ty + 1)), totals=nd(ti.i64, (B,)),
                   hist=nd(ti.i32, (B, RADIX)), cursor=nd(ti.i32, (B, tx * ty)))


@dataclass
class WindowGradBuffers:
    """Scratch of the cs gradient (``kernels/window_grad.py``) for B poses at H x W."""

    h: ti.Ndarray  # [B, H, W, 3, 3]
    wts: ti.Ndarray  # [B, H, W, 6]
    means: ti.Ndarray  # [B, H, W, 6]
    rows: ti.Ndarray  # [B, H, 1, 2]
    tmp6: ti.Ndarray  # [B, H, W, 6]
    hat: ti.Ndarray  # [B, H, W, 6]
    tmpj: ti.Ndarray  # [B, H, W, 3 * NXI]
    jbar: ti.Ndarray  # [B, H, W, 3 * NXI]
    sys: ti.Ndarray  # [B, H, 1, NSYS]
    out2: ti.Ndarray  # [B, 2]
    outs: ti.Ndarray  # [B, NSYS]

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> WindowGradBuffers:
        nd = ti.ndarray
        return cls(nd(ti.f32, (B, H, W, 3, 3)), nd(ti.f32, (B, H, W, 6)), nd(ti.f32, (B, H, W, 6)),
                   nd(ti.f32, (B, H, 1, 2)), nd(ti.f32, (B, H, W, 6)), nd(ti.f32, (B, H, W, 6)),
                   nd(ti.f32, (B, H, W, 3 * NXI)), nd(ti.f32, (B, H, W, 3 * NXI)),
                   nd(ti.f32, (B, H, 1, window_grad.NSYS)), nd(ti.f64, (B, 2)), nd(ti.f64, (B, window_grad.NSYS)))


@dataclass
class DerivativeWorkspace:
    """The derivative pass's images at one size: rgb [B, H, W, 3], alpha [B, H, W], drgb [B, H, W, 3 * NXI]
    (colour derivatives in ``xi = (w, v)``), and the cs gradient's scratch, made on first use."""

    batch: int
    rgb: ti.Ndarray
    alpha: ti.Ndarray
    drgb: ti.Ndarray
    window: WindowGradBuffers | None = None

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> DerivativeWorkspace:
        nd = ti.ndarray
        return cls(B, nd(ti.f32, (B, H, W, 3)), nd(ti.f32, (B, H, W)), nd(ti.f32, (B, H, W, 3 * NXI)))


@dataclass
class TileLists:
    """The tile lists of the last launch: isect [capacity] (resident Gaussian index per entry), with the parallel
    sort's keys (int64) and ids (int32) beside it (torch; None for the serial sort)."""

    isect: object
    capacity: int
    keys: object = None
    ids: object = None


@dataclass
class Pool:
    """Device buffers shared by a renderer and every working set taken from it (``Renderer.subset``): a query's
    working set (a different size per query) reuses the last one's buffers instead of allocating its own.

    ``records`` and ``derivative_records`` are one set for every image size (calls run one at a time);
    ``workspaces`` are keyed by (width, height, tile size), ``derivative_workspaces`` by (width, height)."""

    workspaces: dict[tuple[int, int, int], Workspace] = field(default_factory=dict)
    derivative_workspaces: dict[tuple[int, int], DerivativeWorkspace] = field(default_factory=dict)
    records: ProjectionRecords | None = None
    derivative_records: DerivativeRecords | None = None
    lists: TileLists | None = None

    def grown(self, cur, batch: int, n: int):
        """(batch, columns) for a per-Gaussian set that must hold ``batch`` poses of ``n`` Gaussians, or None when
        ``cur`` already does: columns grow to 1.25x the old when a working set outgrows it, so that a few larger
        ones do not re-allocate each time."""
        if cur is not None and cur.batch >= batch and cur.gaussians >= n:
            return None
        if cur is None:
            return batch, n
        cols = cur.gaussians if cur.gaussians >= n else max(n, int(1.25 * cur.gaussians))
        return max(batch, cur.batch), cols

    def projection_records(self, batch: int, n: int, parallel: bool) -> ProjectionRecords:
        size = self.grown(self.records, batch, n)
        if size is not None:
            self.records = ProjectionRecords.allocate(*size, parallel)
        return self.records

    def derivative_records_for(self, batch: int, n: int) -> DerivativeRecords:
        size = self.grown(self.derivative_records, batch, n)
        if size is not None:
            self.derivative_records = DerivativeRecords.allocate(*size)
        return self.derivative_records

    def tile_lists(self, m: int, parallel: bool) -> TileLists:
        """Tile-list buffers for at least ``m`` entries, grown to 1.25x when too small (the old freed first)."""
        if self.lists is None or m > self.lists.capacity:
            cap = int(max(m, 1 << 16) * 1.25)
            self.lists = None
            if parallel:
                self.lists = TileLists(_torch_zeros(cap, "int32"), cap, _torch_zeros(cap, "int64", False),
                                       _torch_zeros(cap, "int32", False))
            else:
                self.lists = TileLists(ti.ndarray(ti.i32, (cap,)), cap)
        return self.lists
