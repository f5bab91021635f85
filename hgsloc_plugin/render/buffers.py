"""Device buffers of the renderer, as typed records: per-Gaussian records, per-image-size workspaces, the pool.

Shapes use B (poses per launch), n (Gaussians), H x W (image), tx x ty (tiles); every buffer is a Taichi ndarray.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from ..kernels import window_grad
from ..kernels.footprint import RECT_SIZE
from ..kernels.launch import launcher, upload
from ..kernels.layout import Cam, Rec
from ..kernels.pose_grad import NDER, NXI
from ..kernels.radix import DIGITS, MAX_BLOCKS
from ..kernels.readback import readback_kernel
from .prepare import upload as upload_array

logger = logging.getLogger("hgsloc_plugin.render")

_HOST_DTYPES = {ti.f32: np.float32, ti.f64: np.float64, ti.i32: np.int32, ti.i64: np.int64}


def read_rows(arr: ti.Ndarray, n: int) -> np.ndarray:
    """The first ``n`` rows of a device array [B, ...] as a host array [n, ...] (``kernels/readback.py``: a
    workspace's ``to_numpy`` copies all B poses)."""
    out = np.empty((n,) + tuple(arr.shape[1:]), _HOST_DTYPES[arr.dtype])
    launcher(readback_kernel())(arr, out)
    return out


def blend_mode(requested: str, arch: str) -> str:
    """The image blend a renderer uses (``RasterConfig.blend``) on backend ``arch``: for "auto", "pixel" on CUDA
    (one thread per pixel) and "splat" on the CPU (one task per tile, each Gaussian visiting its own pixels)."""
    if requested == "auto":
        return "pixel" if arch == "cuda" else "splat"
    return requested


def sort_mode(requested: str, arch: str) -> str:
    """The tile sort a renderer uses (``RasterConfig.sort``) on backend ``arch``: for "auto", "parallel" on CUDA
    (one thread per Gaussian and tile, a device radix sort) and "serial" on the CPU (one thread per pose)."""
    if requested == "auto":
        return "parallel" if arch == "cuda" else "serial"
    return requested


@dataclass
class ProjectionRecords:
    """Per-Gaussian outputs of the projection and the tile sort, [B, n, ...]; one set serves every image size.

    Attributes:
        depth [B, n]; rect [B, n, RECT_SIZE] (tile box and footprint mask, ``kernels/footprint.py``); ntiles
        [B, n] (tiles in the footprint; 0: culled); packed [B, n, Rec.SIZE]
        (the blend's record per Gaussian); keys / boxes [2, B, n] u64: the serial sort's scratch
        (``kernels/tile_sort.py``); offsets [B * n + 1]: the parallel sort's prefix sum of ``ntiles`` (None for
        the other sort).
    """

    batch: int
    gaussians: int
    depth: object
    rect: object
    ntiles: object
    packed: ti.Ndarray
    keys: ti.Ndarray | None = None
    boxes: ti.Ndarray | None = None
    offsets: ti.Ndarray | None = None

    @classmethod
    def allocate(cls, B: int, n: int, parallel: bool) -> ProjectionRecords:
        nd = ti.ndarray
        common = (B, n, nd(ti.f32, (B, n)), nd(ti.i32, (B, n, RECT_SIZE)), nd(ti.i32, (B, n)),
                  nd(ti.f32, (B, n, Rec.SIZE)))
        if parallel:
            return cls(*common, offsets=nd(ti.i64, (B * n + 1,)))
        return cls(*common, nd(ti.u64, (2, B, n)), nd(ti.u64, (2, B, n)))


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
    """The windowed cost's scratch: horizontal pass [B, H, W, 3, 3], row sums [B, H, 1, 2] (the totals per pose
    go straight to a host array)."""

    h: ti.Ndarray
    rows: ti.Ndarray

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> WindowBuffers:
        nd = ti.ndarray
        return cls(nd(ti.f32, (B, H, W, 3, 3)), nd(ti.f32, (B, H, 1, 2)))


@dataclass
class StatBuffers:
    """The fused pixel cost's scratch: per-run statistics [B, rows, tx, Stat.SIZE] (the totals per pose go straight
    to a host array)."""

    runs: ti.Ndarray


@dataclass
class Workspace:
    """Buffers of one image size and tiling for up to ``batch`` poses: the poses and intrinsics uploaded, the tile
    lists' starts [B, tx * ty + 1] and offsets isect_base [B], the serial sort's counters (cursor [B, tx * ty])
    or the parallel sort's tile counts [B * tx * ty], and, made on first
    use, the blended images and the cost scratch."""

    batch: int
    tile: int
    tiles: tuple[int, int]
    viewmats: ti.Ndarray  # [B, 4, 4]: rows 0-2 world-to-camera [R | t], row 3 the camera centre (then 0)
    intrin: ti.Ndarray  # [B, 6]: each pose's fx, fy, cx, cy, dilation, filter (``RasterConfig.widening``)
    extent: ti.Ndarray  # [B, 2]: the projection's extent coefficients of each pose's camera
    cams: ti.Ndarray  # [B, Cam.SIZE]: the camera records the projection writes (``kernels.layout.Cam``)
    isect_base: ti.Ndarray  # [B]
    background: ti.Ndarray  # [3]
    tile_start: ti.Ndarray
    cursor: ti.Ndarray | None = None
    tile_counts: ti.Ndarray | None = None
    images: ImageBuffers | None = None
    window: WindowBuffers | None = None
    stats: StatBuffers | None = None
    sent: dict[str, bytes] = field(default_factory=dict)

    def upload(self, name: str, values: np.ndarray) -> None:
        """Copy ``values`` into the buffer ``name`` unless it already holds them: each upload is a kernel launch,
        and a query's calls repeat the same intrinsics, extent, background and list offsets."""
        data = values.tobytes()
        if self.sent.get(name) != data:
            upload(getattr(self, name), values)
            self.sent[name] = data

    @classmethod
    def allocate(cls, B: int, width: int, height: int, tile: int, parallel: bool) -> Workspace:
        tx, ty = -(-width // tile), -(-height // tile)
        if max(tx, ty) >= 1 << 15:  # the sort packs tile ranges in 16 bits
            raise ValueError(f"image {width}x{height} has too many tiles per axis")
        nd = ti.ndarray
        common = dict(batch=B, tile=tile, tiles=(tx, ty), viewmats=nd(ti.f32, (B, 4, 4)),
                      intrin=nd(ti.f32, (B, 6)), extent=nd(ti.f32, (B, 2)), cams=nd(ti.f32, (B, Cam.SIZE)),
                      isect_base=nd(ti.i64, (B,)),
                      background=nd(ti.f32, (3,)), tile_start=nd(ti.i32, (B, tx * ty + 1)))
        if parallel:
            return cls(**common, tile_counts=nd(ti.i32, (B * tx * ty,)))
        return cls(**common, cursor=nd(ti.i32, (B, tx * ty)))


@dataclass
class WindowGradBuffers:
    """Scratch of the cs gradient (``kernels/window_grad.py``) for B poses at H x W."""

    h: ti.Ndarray  # [B, H, W, 3, 3]
    wts: ti.Ndarray  # [B, H, W, window_grad.NW]
    means: ti.Ndarray  # [B, H, W, 6]
    rows: ti.Ndarray  # [B, H, 1, ROW_SYS + NSYS]: per row, cs_terms' sums then the system's
    tmpw: ti.Ndarray  # [B, H, W, window_grad.NW]
    hat: ti.Ndarray  # [B, H, W, window_grad.NW]
    tmpj: ti.Ndarray  # [B, H, W, 3 * NXI]
    jbar: ti.Ndarray  # [B, H, W, 3 * NXI]

    @classmethod
    def allocate(cls, B: int, H: int, W: int) -> WindowGradBuffers:
        nd = ti.ndarray
        k, nw = window_grad.ROW_SYS + window_grad.NSYS, window_grad.NW
        return cls(nd(ti.f32, (B, H, W, 3, 3)), nd(ti.f32, (B, H, W, nw)), nd(ti.f32, (B, H, W, 6)),
                   nd(ti.f32, (B, H, 1, k)), nd(ti.f32, (B, H, W, nw)), nd(ti.f32, (B, H, W, nw)),
                   nd(ti.f32, (B, H, W, 3 * NXI)), nd(ti.f32, (B, H, W, 3 * NXI)))


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
    """The tile lists of the last launch: isect [capacity] (resident Gaussian index per entry). For the parallel
    sort, its keys (int64) and ids (int32) and their radix-sort twins; ``isect`` is then whichever ids buffer
    the sort ended in. ``masks`` [capacity] (uint64): the derivative pass's pixel masks, allocated on first use
    (``Pool.pixel_masks``)."""

    isect: ti.Ndarray
    capacity: int
    keys: ti.Ndarray | None = None
    ids: ti.Ndarray | None = None
    keys_tmp: ti.Ndarray | None = None
    ids_tmp: ti.Ndarray | None = None
    masks: ti.Ndarray | None = None


@dataclass
class SortScratch:
    """The parallel sort's fixed scratch (``kernels/radix.py``): per-pass digit counts [DIGITS, MAX_BLOCKS], their
    scan [DIGITS * MAX_BLOCKS + 1] and block sums [MAX_BLOCKS + 1]."""

    counts: ti.Ndarray
    offsets: ti.Ndarray
    sums: ti.Ndarray

    @classmethod
    def allocate(cls) -> SortScratch:
        return cls(ti.ndarray(ti.i32, (DIGITS, MAX_BLOCKS)), ti.ndarray(ti.i64, (DIGITS * MAX_BLOCKS + 1,)),
                   ti.ndarray(ti.i64, (MAX_BLOCKS + 1,)))


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
    sort_scratch: SortScratch | None = None
    query_indices: dict[bytes, ti.Ndarray] = field(default_factory=dict)
    placeholders: dict[str, ti.Ndarray] = field(default_factory=dict)

    def query_index(self, index: np.ndarray) -> ti.Ndarray:
        """``index`` [B] (int32: each pose's query slot) on the device; the last few are kept, a lockstep batch
        repeats the same few."""
        index = np.ascontiguousarray(index, np.int32)
        key = index.tobytes()
        nd = self.query_indices.get(key)
        if nd is None:
            if len(self.query_indices) >= 64:
                self.query_indices.clear()
            nd = self.query_indices[key] = upload_array(index if index.size else np.zeros(1, np.int32), ti.i32)
        return nd

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
            nd = ti.ndarray
            if parallel:
                ids = nd(ti.i32, (cap,))
                self.lists = TileLists(ids, cap, nd(ti.i64, (cap,)), ids, nd(ti.i64, (cap,)), nd(ti.i32, (cap,)))
            else:
                self.lists = TileLists(nd(ti.i32, (cap,)), cap)
        return self.lists

    def pixel_masks(self) -> ti.Ndarray:
        """One uint64 per entry of the current tile lists (``kernels.pose_grad.pixel_masks``)."""
        if self.lists.masks is None:
            self.lists.masks = ti.ndarray(ti.u64, (self.lists.capacity,))
        return self.lists.masks

    def placeholder(self, dtype) -> ti.Ndarray:
        """A one-entry device array of ``dtype`` for a kernel argument the launch does not read (the projection's
        ``totals`` under the parallel sort, the masks of a derivative pass without them): a host array there
        would be copied to and from the device at each launch, a full buffer would waste its memory."""
        key = str(dtype)
        if key not in self.placeholders:
            self.placeholders[key] = ti.ndarray(dtype, (1,))
        return self.placeholders[key]

    def radix_scratch(self) -> SortScratch:
        if self.sort_scratch is None:
            self.sort_scratch = SortScratch.allocate()
        return self.sort_scratch
