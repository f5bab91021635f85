"""Python entry points of the Taichi 3DGS renderer: ``render``, ``render_full`` and ``render_cost``.

A :class:`Renderer` keeps one scene's Gaussians resident on the Taichi device and reuses per-camera workspaces, so
repeated calls neither re-upload the scene nor recompile (kernels take ndarrays of any shape). It holds no
reference to the :class:`GaussianScene` itself, so the per-scene cache (:func:`get_renderer`) lets a scene go
when its caller drops it. All poses of
one call go through each kernel stage in one launch (the batch is a leading dimension); a batch larger than
``RasterConfig.max_batch_elements`` (poses x Gaussians) is split into chunks.
"""

from __future__ import annotations

import functools
import logging
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import taichi as ti

from .backend import current_arch
from .camera import Camera
from .costs import cost_from_window
from .kernels import RasterConfig, cull, window, window_grad
from .kernels.blend import cost_kernel, image_kernel, reduce_kernel, splat_cost_kernel, splat_image_kernel
from .kernels.layout import Rec, Stat
from .kernels.pose_grad import NDER, NXI, blend_grad_kernel, projection_grad_kernel
from .kernels.projection import projection_kernel
from .kernels.readback import readback_kernel
from .kernels.tile_sort import RADIX, bin_parallel, count_kernel, tile_sort_kernel
from .pose import Pose
from .scene import GaussianScene

logger = logging.getLogger(__name__)


def covariances_3d(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Upper triangle of Sigma = R S S^T R^T per Gaussian: [N, 6] (xx, xy, xz, yy, yz, zz), float32.

    Args:
        quats: unit quaternions w, x, y, z [N, 4]; scales: [N, 3].
    """
    q = quats.astype(np.float64)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)
    M = R * scales.astype(np.float64)[:, None, :]
    S = M @ M.transpose(0, 2, 1)
    return np.stack([S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]], 1).astype(np.float32)


def morton_order(means: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation [N] that sorts centres [N, 3] along a Z-order curve over their bounding box (stable)."""
    m = np.asarray(means, np.float64)
    lo, hi = m.min(axis=0), m.max(axis=0)
    q = ((m - lo) / np.maximum(hi - lo, 1e-12) * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(m), np.uint64)
    for bit in range(bits):
        for a in range(3):
            code |= ((q[:, a] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + a)
    return np.argsort(code, kind="stable")


def as_pose_list(poses) -> tuple[list[Pose], bool]:
    """Normalise a Pose or a sequence of Poses; returns (list, was_single)."""
    if isinstance(poses, Pose):
        return [poses], True
    if isinstance(poses, Sequence) or hasattr(poses, "__iter__"):
        out = list(poses)
        for k, p in enumerate(out):
            if not isinstance(p, Pose):
                raise TypeError(f"poses[{k}] must be a Pose, got {type(p).__name__}")
        if not out:
            raise ValueError("poses is empty")
        return out, False
    raise TypeError(f"poses must be a Pose or a list of Poses, got {type(poses).__name__}")


@dataclass
class _Workspace:
    batch: int
    bufs: dict
    gaussians: int = 0  # columns of the per-Gaussian buffers (>= the renderer's n; 0 for a per-size workspace)


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


def _torch_device() -> str:
    return "cuda" if current_arch() == "cuda" else "cpu"


def _projection_records(B: int, n: int, parallel: bool = False) -> dict:
    """Per-Gaussian buffers of the projection and the tile sort for B poses of n Gaussians ([B, n, ...]); for the
    parallel sort (``RasterConfig.sort``) the projection's depth, rect and ntiles are torch tensors on the Taichi
    device, which the Taichi kernels read and write in place, and the serial sort's scratch is not needed."""
    nd = ti.ndarray
    if parallel:
        import torch

        dev = _torch_device()
        return dict(depth=torch.zeros((B, n), dtype=torch.float32, device=dev),
                    rect=torch.zeros((B, n, 4), dtype=torch.int32, device=dev),
                    ntiles=torch.zeros((B, n), dtype=torch.int32, device=dev), packed=nd(ti.f32, (B, n, Rec.SIZE)))
    return dict(depth=nd(ti.f32, (B, n)), rect=nd(ti.i32, (B, n, 4)), ntiles=nd(ti.i32, (B, n)),
                packed=nd(ti.f32, (B, n, Rec.SIZE)), keys_a=nd(ti.u32, (B, n)), keys_b=nd(ti.u32, (B, n)),
                ids_a=nd(ti.i32, (B, n)), ids_b=nd(ti.i32, (B, n)), rects=nd(ti.i32, (4, B, n)))


def _derivative_records(B: int, n: int) -> dict:
    """Per-Gaussian derivative records for B poses of n Gaussians: dpacked [B, n, NDER]."""
    return {"dpacked": ti.ndarray(ti.f32, (B, n, NDER))}


@dataclass
class _Pool:
    """Device workspaces shared by a renderer and every working set taken from it (``Renderer.subset``): a
    query's working set (a different size per query, re-selected as the search moves) reuses the buffers of
    the last one instead of allocating and zero-filling its own (at 1M Gaussians about 0.7 s per query).

    The per-Gaussian buffers (``records``: projection and sort, ``derivative_records``) are one set for every
    image size, since calls run one at a time; the per-size workspaces (``ws``, ``gws``) hold the image- and
    tile-sized buffers and a reference to that set."""

    ws: dict = field(default_factory=dict)  # (width, height, tile size) -> _Workspace
    gws: dict = field(default_factory=dict)  # derivative workspaces, (width, height) -> _Workspace
    records: _Workspace | None = None
    derivative_records: _Workspace | None = None
    isect: ti.Ndarray | None = None  # a torch tensor with the parallel sort, beside its keys and ids
    isect_cap: int = 0
    keys: object = None
    ids: object = None


class Renderer:
    """One scene's Gaussians resident on the Taichi device.

    Example:
        >>> r = Renderer(scene)
        >>> rgb, alpha, depth = r.render_full(camera, [T1, T2])        # [2, H, W, 3], [2, H, W], [2, H, W]
    """

    MIN_WORKSPACE = 14  # poses: a search expansion's children (12 moves, a pattern move) fit

    def __init__(self, scene: GaussianScene, config: RasterConfig | None = None):
        current_arch()
        self.config = config or RasterConfig()
        n = scene.num_gaussians
        if n == 0:
            raise ValueError("scene has no Gaussians")
        self.n = n
        self.sh_degree = scene.sh_degree
        # Resident in Morton (Z-curve) order of the centres: the Gaussians of one tile then sit close together
        # in memory, which the projection, sort and blend read by index (measured on a 1M-Gaussian map in
        # ply order vs shuffled vs Morton: 1.7x from shuffled). Only exact depth ties blend in another order.
        self.source_index = morton_order(scene.means)  # [n]: resident index -> scene index
        o = self.source_index
        self._means = self._upload(scene.means[o], ti.f32)
        self._cov3d = self._upload(covariances_3d(scene.quats[o], scene.scales[o]), ti.f32)
        self._opac = self._upload(scene.opacities[o], ti.f32)
        self._sh = self._upload(scene.sh[o], ti.f32)
        self._smax = self._upload(scene.scales[o].max(axis=1).astype(np.float32), ti.f32)
        self._init_state()
        self._project = projection_kernel(self.config, self.sh_degree)
        self._count = count_kernel()
        self._sort = tile_sort_kernel(self.config)
        mode = self.config.blend
        if mode == "auto":
            mode = "pixel" if current_arch() == "cuda" else "splat"
        self.blend_mode = mode
        if mode == "splat":
            self._blend_img = splat_image_kernel(self.config)
            self._blend_cost = splat_cost_kernel(self.config)
        else:
            self._blend_img = image_kernel(self.config)
            self._blend_cost = cost_kernel(self.config)
        self._reduce = reduce_kernel()
        self.sort_mode = sort_mode(self.config.sort, current_arch())

    def _init_state(self) -> None:
        self._pool = _Pool()

    def _shared(self, attr: str, batch: int, make) -> dict:
        """The pool's per-Gaussian buffers ``attr`` (``records`` or ``derivative_records``, made by ``make(B, n)``)
        for ``batch`` poses of this renderer's Gaussians. One set serves every image size: per size, the 1M
        room's gradient route (three sizes) held three copies of ~340 MB. It grows when a call needs more poses
        or Gaussians (columns: 1.25x the old when a working set outgrows it, so that a few larger ones do not
        re-allocate each time), and the workspaces that referenced the old set get the new one."""
        pool = self._pool
        cur = getattr(pool, attr)
        if cur is not None and cur.batch >= batch and cur.gaussians >= self.n:
            return cur.bufs
        n = self.n
        if cur is not None:
            n = cur.gaussians if cur.gaussians >= self.n else max(self.n, int(1.25 * cur.gaussians))
            batch = max(batch, cur.batch)
        new = _Workspace(batch, make(batch, n), n)
        setattr(pool, attr, new)
        for ws in (*pool.ws.values(), *pool.gws.values()):  # no workspace keeps the old set alive
            ws.bufs.update({k: v for k, v in new.bufs.items() if k in ws.bufs})
        return new.bufs

    def working_set(self, cameras: Sequence[Camera], pose: Pose, max_t: float, max_r_deg: float) -> Renderer:
        """A renderer of the Gaussians that some pose of a region can see (``kernels/cull.py``).

        Args:
            cameras: every camera (size, intrinsics) the caller will render with.
            pose: the region's centre pose (world-to-camera).
            max_t / max_r_deg: camera-centre shift (scene units) and rotation (degrees) bounding the region.

        Returns:
            A :class:`Renderer` over the kept Gaussians (same order, same kernels; on the device, only the index
            list crosses), or ``self`` when nearly all are kept (or none). For every pose of the region its
            images and costs equal this renderer's bit for bit; ``.n`` is the number kept.
        """
        rows, fac = cull.planes(cameras, self.config)
        keep = ti.ndarray(ti.i32, (self.n,))
        cull.keep_kernel(self.config)(self._means, self._smax, self._opac,
                                      self._upload(pose.matrix34().astype(np.float64), ti.f64),
                                      self._upload(np.array(rows, np.float64), ti.f64),
                                      self._upload(np.array(fac, np.float64), ti.f64), float(max_t),
                                      float(np.radians(max_r_deg)), keep)
        idx = np.flatnonzero(keep.to_numpy()).astype(np.int32)
        if idx.size >= 0.95 * self.n or idx.size == 0:
            return self
        return self.subset(idx)

    def subset(self, idx: np.ndarray) -> Renderer:
        """A renderer of the resident Gaussians ``idx`` [M] (increasing resident indices), gathered on the
        device; its ``source_index`` maps them to the scene."""
        idx = np.asarray(idx, np.int32)
        if idx.ndim != 1 or idx.size == 0 or np.any(np.diff(idx) <= 0) or idx[0] < 0 or idx[-1] >= self.n:
            raise ValueError("subset indices must be a non-empty increasing list of Gaussian indices")
        sub = self._sibling(int(idx.size), self.source_index[idx])
        nd_idx = self._upload(idx, ti.i32)
        for name in ("_means", "_cov3d", "_opac", "_sh", "_smax"):
            src = getattr(self, name)
            dst = ti.ndarray(ti.f32, (idx.size,) + tuple(src.shape[1:]))
            cull.gather_kernel(len(src.shape))(src, nd_idx, dst)
            setattr(sub, name, dst)
        return sub

    def _sibling(self, n: int, source_index: np.ndarray) -> Renderer:
        """A renderer of ``n`` other Gaussians (their arrays set by the caller) with this one's config, compiled
        kernels and workspaces (the pool: kernels take N as an argument or read it from the Gaussians)."""
        sub = object.__new__(Renderer)
        sub.__dict__.update({k: v for k, v in self.__dict__.items() if not k.startswith("_") or k in (
            "_project", "_count", "_sort", "_blend_img", "_blend_cost", "_reduce", "_pool")})
        sub.n = n
        sub.source_index = np.asarray(source_index)
        return sub

    def arrays(self) -> dict[str, np.ndarray]:
        """Host copies of the resident Gaussians, in resident order: ``means`` [n, 3], ``cov3d`` [n, 6]
        (xx, xy, xz, yy, yz, zz), ``opacities`` [n], ``sh`` [n, K, 3], ``smax`` [n] (bound on the std. dev.)."""
        return {"means": self._means.to_numpy(), "cov3d": self._cov3d.to_numpy(), "opacities": self._opac.to_numpy(),
                "sh": self._sh.to_numpy(), "smax": self._smax.to_numpy()}

    def derived(self, arrays: dict[str, np.ndarray], source_index: np.ndarray) -> Renderer:
        """A renderer of other Gaussians (``arrays`` as from :meth:`arrays`, resident in the order given) with
        this one's config, kernels and workspaces; ``source_index`` [m]: scene index per Gaussian (-1: none)."""
        m = len(arrays["means"])
        if m == 0:
            raise ValueError("no Gaussians")
        sub = self._sibling(m, source_index)
        sub._means = self._upload(arrays["means"].astype(np.float32), ti.f32)
        sub._cov3d = self._upload(arrays["cov3d"].astype(np.float32), ti.f32)
        sub._opac = self._upload(arrays["opacities"].astype(np.float32), ti.f32)
        sub._sh = self._upload(arrays["sh"].astype(np.float32), ti.f32)
        sub._smax = self._upload(arrays["smax"].astype(np.float32), ti.f32)
        return sub

    @staticmethod
    def _upload(a: np.ndarray, dtype) -> ti.Ndarray:
        a = np.ascontiguousarray(a)
        nd = ti.ndarray(dtype, shape=a.shape)
        nd.from_numpy(a)
        return nd

    @property
    def chunk(self) -> int:
        """Poses per launch."""
        return max(1, self.config.max_batch_elements // self.n)

    def _workspace(self, camera: Camera, batch: int, grad: bool = False) -> _Workspace:
        """The buffers for up to ``batch`` poses at ``camera``'s size: one workspace per image size (and tiling:
        ``grad`` for the derivative pass's, ``RasterConfig.grad_tile_size``), reused by every call that fits
        (kernels take the pose count as an argument), grown when a call needs more, with the pool's per-Gaussian
        buffers (:meth:`_shared`). A search's batches vary from 1 to 13 poses; re-allocating per size cost 35-70
        ms at 50k Gaussians and about 1 s at 1M (allocation zero-fills), more than the renders of an expansion."""
        ts = self.config.grad_tile_size if grad else self.config.tile_size
        key = (camera.width, camera.height, ts)
        ws = self._pool.ws.get(key)
        if ws is None or ws.batch < batch:
            B = max(batch, min(self.chunk, self.MIN_WORKSPACE), ws.batch if ws is not None else 0)
            tx, ty = -(-camera.width // ts), -(-camera.height // ts)
            if max(tx, ty) >= 1 << 15:  # the sort packs tile ranges in 16 bits
                raise ValueError(f"image {camera.width}x{camera.height} has too many tiles per axis")
            nd = ti.ndarray
            bufs = dict(
                viewmats=nd(ti.f32, (B, 3, 4)), campos=nd(ti.f32, (B, 3)), intrin=nd(ti.f32, (4,)),
                extent=nd(ti.f32, (2,)), isect_base=nd(ti.i64, (B,)), background=nd(ti.f32, (3,)), tile=ts,
                tiles=(tx, ty),
            )
            if self.sort_mode == "parallel":
                import torch

                bufs["tile_start"] = torch.zeros((B, tx * ty + 1), dtype=torch.int32, device=_torch_device())
            else:
                bufs.update(totals=nd(ti.i64, (B,)), hist=nd(ti.i32, (B, RADIX)), cursor=nd(ti.i32, (B, tx * ty)),
                            tile_start=nd(ti.i32, (B, tx * ty + 1)))
            ws = _Workspace(B, bufs)
            self._pool.ws[key] = ws
        ws.bufs.update(self._shared("records", ws.batch, functools.partial(
            _projection_records, parallel=self.sort_mode == "parallel")))
        return ws

    def _geometry(self, camera: Camera, poses: list[Pose], ws: _Workspace, background) -> None:
        """Projection and tile sort for up to ``ws.batch`` poses, binned at the workspace's tile size (the one
        projection and sort kernel serve the renders' tiles and the derivative pass's)."""
        b = ws.bufs
        B = len(poses)
        vm = np.zeros((ws.batch, 3, 4), np.float32)
        cp = np.zeros((ws.batch, 3), np.float32)
        for k, T in enumerate(poses):
            vm[k] = T.matrix34()
            cp[k] = T.centre()
        b["viewmats"].from_numpy(vm)
        b["campos"].from_numpy(cp)
        b["intrin"].from_numpy(np.array([camera.fx, camera.fy, camera.cx, camera.cy], np.float32))
        b["extent"].from_numpy(np.array([cull.extent_coefficient(*cull.jacobian_limits(camera)),
                                         cull.extent_pixels(self.config) / min(camera.fx, camera.fy)], np.float32))
        b["background"].from_numpy(np.asarray(background, np.float32).reshape(3))
        tx, ty = b["tiles"]
        self._project(self._means, self._cov3d, self._opac, self._sh, self._smax, b["viewmats"], b["campos"],
                      b["intrin"], camera.width, camera.height, b["tile"], B, b["extent"], b["depth"], b["rect"],
                      b["ntiles"], b["packed"])
        parallel = self.sort_mode == "parallel"
        if parallel:
            totals = bin_parallel(b["depth"], b["rect"], b["ntiles"], B, self.n, tx, tx * ty, self._list_buffers,
                                  b["tile_start"])
        else:
            self._count(b["ntiles"], B, self.n, b["totals"])
            totals = read_rows(b["totals"], B)
        base = np.zeros(ws.batch, np.int64)
        base[1:B] = np.cumsum(totals)[:-1]
        b["isect_base"].from_numpy(base)
        if not parallel:
            _, _, isect = self._list_buffers(int(totals.sum()))
            self._sort(b["depth"], b["rect"], b["ntiles"], b["isect_base"], tx, ty, B, self.n, b["keys_a"],
                       b["keys_b"], b["ids_a"], b["ids_b"], b["rects"], b["hist"], b["cursor"], b["tile_start"],
                       isect)

    def _list_buffers(self, m: int):
        """The pool's tile-list buffer ``isect`` for at least ``m`` entries, with the parallel sort's key and id
        buffers beside it (torch; None for the serial sort): (keys, ids, isect), grown to 1.25x when too small."""
        pool = self._pool
        if pool.isect is None or m > pool.isect_cap:
            cap = int(max(m, 1 << 16) * 1.25)
            pool.isect = pool.keys = pool.ids = None  # free the old ones first
            if self.sort_mode == "parallel":
                import torch

                dev = _torch_device()
                pool.keys = torch.empty(cap, dtype=torch.int64, device=dev)
                pool.ids = torch.empty(cap, dtype=torch.int32, device=dev)
                pool.isect = torch.zeros(cap, dtype=torch.int32, device=dev)
            else:
                pool.isect = ti.ndarray(ti.i32, (cap,))
            pool.isect_cap = cap
        return pool.keys, pool.ids, pool.isect

    def _chunks(self, poses: list[Pose], size: int | None = None):
        """Consecutive parts of ``poses`` of at most ``size`` (default: ``chunk``) poses."""
        c = size or self.chunk
        for s in range(0, len(poses), c):
            yield poses[s:s + c]

    def _blend_images(self, camera: Camera, part: list[Pose], background, batch: int) -> dict:
        """Geometry and image blending of up to one chunk of poses; the images stay on the device (in the
        workspace's ``rgb``, ``alpha`` and ``dimg``). ``batch``: the workspace size (poses of the whole call,
        capped at one chunk), so every chunk of a call shares one workspace."""
        ws = self._workspace(camera, batch)
        b = ws.bufs
        if "rgb" not in b:
            H, W = camera.height, camera.width
            b["rgb"] = ti.ndarray(ti.f32, (ws.batch, H, W, 3))
            b["alpha"] = ti.ndarray(ti.f32, (ws.batch, H, W))
            b["dimg"] = ti.ndarray(ti.f32, (ws.batch, H, W))
        self._geometry(camera, part, ws, background)
        tx, ty = b["tiles"]
        if self.blend_mode == "splat":
            self._blend_img(b["packed"], b["tile_start"], self._pool.isect, b["isect_base"], b["background"], tx, ty,
                            len(part), b["rgb"], b["alpha"], b["dimg"])
        else:
            self._blend_img(b["packed"], b["tile_start"], self._pool.isect, b["isect_base"], b["background"], tx,
                            len(part), b["rgb"], b["alpha"], b["dimg"])
        return b

    def visible(self, camera: Camera, poses: list[Pose]) -> np.ndarray:
        """Which Gaussians the projection keeps (touch at least one tile) for each pose: bool [B, n], in the
        order of ``source_index`` (scene indices)."""
        out = []
        for part in self._chunks(poses):
            ws = self._workspace(camera, min(len(poses), self.chunk))
            self._geometry(camera, part, ws, (0.0, 0.0, 0.0))
            out.append(read_rows(ws.bufs["ntiles"], len(part)) > 0)
        return np.concatenate(out)

    def render_full(self, camera: Camera, poses: list[Pose], background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W] and accumulated depth [B, H, W] (float32 numpy)."""
        rgbs, alphas, depths = [], [], []
        for part in self._chunks(poses):
            b = self._blend_images(camera, part, background, min(len(poses), self.chunk))
            n = len(part)
            rgbs.append(read_rows(b["rgb"], n))
            alphas.append(read_rows(b["alpha"], n))
            depths.append(read_rows(b["dimg"], n))
        return np.concatenate(rgbs), np.concatenate(alphas), np.concatenate(depths)

    @staticmethod
    def upload_window_query(image: np.ndarray) -> ti.Ndarray:
        """Query statistics for :meth:`window_cost`: windowed mean and variance per channel, on the device
        ([H, W, 3, window.NQ]; ``image`` [H, W, 3] float in [0, 1])."""
        q = Renderer.upload_image(image)
        H, W = q.shape[:2]
        out = ti.ndarray(ti.f32, (H, W, 3, window.NQ))
        window.query_stats_kernel()(q, out)
        return out

    def window_cost(self, camera: Camera, poses: list[Pose], qstats: ti.Ndarray, background=(0.0, 0.0, 0.0),
                    mask_alpha: float = 0.0, luminance: bool = False) -> np.ndarray:
        """Windowed structural similarity of each pose's rendering with the query: [B, 2] float64, the sum over
        valid pixels of the per-pixel value (``cs``, or full SSIM when ``luminance``) and the valid pixel count.

        Args:
            qstats: from :meth:`upload_window_query`, at the camera's size.
        """
        if tuple(qstats.shape[:2]) != (camera.height, camera.width):
            raise ValueError(f"query statistics are {tuple(qstats.shape[:2])}, camera needs "
                             f"({camera.height}, {camera.width})")
        out = []
        for part in self._chunks(poses):
            b = self._blend_images(camera, part, background, min(len(poses), self.chunk))
            if "win_h" not in b:
                B, H, W = b["alpha"].shape
                b["win_h"] = ti.ndarray(ti.f32, (B, H, W, 3, 3))
                b["win_rows"] = ti.ndarray(ti.f32, (B, H, 1, 2))
                b["win_out"] = ti.ndarray(ti.f64, (B, 2))
            n = len(part)
            window.horizontal_kernel()(b["rgb"], qstats, n, b["win_h"])
            window.vertical_cost_kernel(bool(luminance))(b["win_h"], qstats, b["alpha"], float(mask_alpha), n,
                                                         b["win_rows"])
            self._reduce(b["win_rows"], n, b["win_out"])
            out.append(read_rows(b["win_out"], n))
        return np.concatenate(out)

    @staticmethod
    def upload_image(image: np.ndarray) -> ti.Ndarray:
        """A comparison image [H, W, 3] (float32 in [0, 1]) on the device, for :meth:`cost_stats`."""
        image = np.ascontiguousarray(image, dtype=np.float32)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"comparison image must be [H, W, 3], got {image.shape}")
        nd = ti.ndarray(ti.f32, image.shape)
        nd.from_numpy(image)
        return nd

    def cost_stats(self, camera: Camera, poses: list[Pose], target: ti.Ndarray, background=(0.0, 0.0, 0.0),
                   mask_alpha: float = 0.0) -> np.ndarray:
        """Photometric statistics of each pose's rendering against ``target``: [B, Stat.SIZE] float64.

        Args:
            target: the comparison image from :meth:`upload_image`, at the camera's size.

        The layout is ``kernels.layout.Stat`` (n_valid, SAD, SSD, per-channel sums).
        """
        if tuple(target.shape) != (camera.height, camera.width, 3):
            raise ValueError(f"comparison image is {tuple(target.shape)}, camera needs "
                             f"({camera.height}, {camera.width}, 3)")
        out = []
        for part in self._chunks(poses):
            ws = self._workspace(camera, min(len(poses), self.chunk))
            b = ws.bufs
            tx, ty = b["tiles"]
            if "run_stats" not in b:
                rows = ty if self.blend_mode == "splat" else camera.height
                b["run_stats"] = ti.ndarray(ti.f32, (ws.batch, rows, tx, Stat.SIZE))
                b["stats"] = ti.ndarray(ti.f64, (ws.batch, Stat.SIZE))
            self._geometry(camera, part, ws, background)
            if self.blend_mode == "splat":
                self._blend_cost(b["packed"], b["tile_start"], self._pool.isect, b["isect_base"], b["background"], tx,
                                 ty, len(part), target, float(mask_alpha), b["run_stats"])
            else:
                self._blend_cost(b["packed"], b["tile_start"], self._pool.isect, b["isect_base"], b["background"], tx,
                                 len(part), target, float(mask_alpha), b["run_stats"])
            self._reduce(b["run_stats"], len(part), b["stats"])
            out.append(read_rows(b["stats"], len(part)))
        return np.concatenate(out)

    # ---- pose derivatives (kernels/pose_grad.py, kernels/window_grad.py) ----

    @property
    def grad_chunk(self) -> int:
        """Poses per derivative launch (the per-Gaussian derivative records take 30 floats per pose)."""
        return max(1, min(4, 4_000_000 // self.n))

    def _grad_workspace(self, camera: Camera, batch: int) -> _Workspace:
        """The derivative pass's image-sized buffers at ``camera``'s size, with the pool's derivative records."""
        key = (camera.width, camera.height)
        ws = self._pool.gws.get(key)
        if ws is None or ws.batch < batch:
            H, W = camera.height, camera.width
            batch = max(batch, ws.batch if ws is not None else 0)
            nd = ti.ndarray
            ws = _Workspace(batch, dict(rgb=nd(ti.f32, (batch, H, W, 3)), alpha=nd(ti.f32, (batch, H, W)),
                                        drgb=nd(ti.f32, (batch, H, W, 3 * NXI))))
            self._pool.gws[key] = ws
        ws.bufs.update(self._shared("derivative_records", ws.batch, _derivative_records))
        return ws

    def _derivative_images(self, camera: Camera, part: list[Pose], background) -> dict:
        """Geometry, derivative records and derivative blending of up to ``grad_chunk`` poses; the images stay on
        the device (``rgb``, ``alpha``, ``drgb`` of the derivative workspace)."""
        ws = self._workspace(camera, len(part), grad=True)
        self._geometry(camera, part, ws, background)
        b = ws.bufs
        g = self._grad_workspace(camera, min(self.grad_chunk, len(part))).bufs
        n = len(part)
        projection_grad_kernel(self.config)(self._means, self._cov3d, b["viewmats"], b["intrin"], camera.width,
                                            camera.height, n, b["ntiles"], g["dpacked"])
        # one task per pixel on every backend: a tile-parallel twin (per-pixel state in a scratch array, as
        # blend.splat_image does) measured 1.7x slower on the CPU here (248 vs 148 ms at 320x240): the
        # derivative arithmetic, not the rejected pairs, dominates, and registers beat the scratch array
        tx, _ = b["tiles"]
        blend_grad_kernel(self.config)(b["packed"], g["dpacked"], b["tile_start"], self._pool.isect, b["isect_base"],
                                       b["background"], tx, n, g["rgb"], g["alpha"], g["drgb"])
        return g

    def render_derivatives(self, camera: Camera, poses: list[Pose], background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W] and the colour's derivatives [B, H, W, 3, 6] with respect to the
        pose increment ``xi = (w, v)`` (``Pose.perturbed_in_camera(w, v)``; ``kernels/pose_grad.py``)."""
        rgbs, alphas, ders = [], [], []
        for part in self._chunks(poses, self.grad_chunk):
            g = self._derivative_images(camera, part, background)
            n = len(part)
            rgbs.append(read_rows(g["rgb"], n))
            alphas.append(read_rows(g["alpha"], n))
            ders.append(read_rows(g["drgb"], n).reshape(n, camera.height, camera.width, 3, NXI))
        return np.concatenate(rgbs), np.concatenate(alphas), np.concatenate(ders)

    def pose_gradient(self, camera: Camera, poses: list[Pose], qstats: ti.Ndarray, background=(0.0, 0.0, 0.0),
                      mask_alpha: float = 0.0):
        """The ``cs`` cost of each pose, its gradient and its Gauss-Newton Hessian in the pose increment
        ``xi = (w, v)`` (``kernels/window_grad.py``); no image leaves the device.

        Args:
            qstats: from :meth:`upload_window_query`, at the camera's size.

        Returns:
            cost [B], grad [B, 6], JtJ [B, 6, 6] (float64); the cost equals :meth:`window_cost`'s ``1 - mean``.
        """
        if tuple(qstats.shape[:2]) != (camera.height, camera.width):
            raise ValueError(f"query statistics are {tuple(qstats.shape[:2])}, camera needs "
                             f"({camera.height}, {camera.width})")
        costs, grads, hessians = [], [], []
        iu = np.triu_indices(NXI)
        for part in self._chunks(poses, self.grad_chunk):
            g = self._derivative_images(camera, part, background)
            n = len(part)
            if "w_rows" not in g:
                B, H, W = g["alpha"].shape
                nd = ti.ndarray
                g.update(w_h=nd(ti.f32, (B, H, W, 3, 3)), w_wts=nd(ti.f32, (B, H, W, 6)),
                         w_means=nd(ti.f32, (B, H, W, 6)), w_rows=nd(ti.f32, (B, H, 1, 2)),
                         w_tmp6=nd(ti.f32, (B, H, W, 6)), w_hat=nd(ti.f32, (B, H, W, 6)),
                         w_tmpj=nd(ti.f32, (B, H, W, 3 * NXI)), w_jbar=nd(ti.f32, (B, H, W, 3 * NXI)),
                         w_sys=nd(ti.f32, (B, H, 1, window_grad.NSYS)), w_out2=nd(ti.f64, (B, 2)),
                         w_outs=nd(ti.f64, (B, window_grad.NSYS)))
            window.horizontal_kernel()(g["rgb"], qstats, n, g["w_h"])
            window_grad.cs_terms_kernel()(g["w_h"], qstats, g["alpha"], float(mask_alpha), n, g["w_wts"],
                                          g["w_means"], g["w_rows"])
            filt = window_grad.filter_kernel
            filt(1, False, 3 * NXI)(g["drgb"], n, g["w_tmpj"])
            filt(0, False, 3 * NXI)(g["w_tmpj"], n, g["w_jbar"])
            filt(0, True, 6)(g["w_wts"], n, g["w_tmp6"])
            filt(1, True, 6)(g["w_tmp6"], n, g["w_hat"])
            window_grad.system_kernel()(g["rgb"], qstats, g["drgb"], g["w_jbar"], g["w_wts"], g["w_hat"],
                                        g["w_means"], n, g["w_sys"])
            self._reduce(g["w_rows"], n, g["w_out2"])
            self._reduce(g["w_sys"], n, g["w_outs"])
            sums = read_rows(g["w_out2"], n)
            sys = read_rows(g["w_outs"], n)
            scale = 2.0 / (3.0 * np.maximum(sums[:, 1], 1.0))
            hess = np.zeros((n, NXI, NXI))
            hess[:, iu[0], iu[1]] = sys[:, :window_grad.NH]
            hess = hess + np.triu(hess, 1).transpose(0, 2, 1)
            costs.append(cost_from_window(sums))
            grads.append(sys[:, window_grad.NH:] * scale[:, None])
            hessians.append(hess * scale[:, None, None])
        return np.concatenate(costs), np.concatenate(grads), np.concatenate(hessians)


_RENDERERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def get_renderer(scene: GaussianScene, config: RasterConfig | None = None) -> Renderer:
    """The cached :class:`Renderer` of a scene (one per scene object and config)."""
    config = config or RasterConfig()
    per_scene = _RENDERERS.setdefault(scene, {})
    r = per_scene.get(config)
    if r is None:
        r = per_scene[config] = Renderer(scene, config)
    return r


def _check(scene, camera):
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"scene must be a GaussianScene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")


def render(scene: GaussianScene, camera: Camera, poses, background=(0.0, 0.0, 0.0), *,
           config: RasterConfig | None = None) -> np.ndarray:
    """Render colour images.

    Args:
        scene: the Gaussians. camera: pinhole intrinsics and size.
        poses: one world-to-camera :class:`Pose` or a list of them.
        background: RGB added with the remaining transmittance.

    Returns:
        float32 [H, W, 3] for one pose, [B, H, W, 3] for a list.
    """
    rgb, _, _ = render_full(scene, camera, poses, background, config=config)
    return rgb


def render_full(scene: GaussianScene, camera: Camera, poses, background=(0.0, 0.0, 0.0), *,
                config: RasterConfig | None = None):
    """Like :func:`render` but returns (rgb [.., H, W, 3], alpha [.., H, W], depth [.., H, W]).

    ``depth`` is the expected camera z of the blended Gaussians (accumulated depth / alpha; 0 where alpha = 0).
    """
    _check(scene, camera)
    plist, single = as_pose_list(poses)
    rgb, alpha, dacc = get_renderer(scene, config).render_full(camera, plist, background)
    depth = np.where(alpha > 0, dacc / np.maximum(alpha, 1e-12), 0.0).astype(np.float32)
    if single:
        return rgb[0], alpha[0], depth[0]
    return rgb, alpha, depth


def render_cost(scene: GaussianScene, camera: Camera, poses, target_image, metric: str = "sad",
                background=(0.0, 0.0, 0.0), *, mask_alpha: float = 0.0, config: RasterConfig | None = None):
    """Image cost of each pose's rendering against ``target_image``, fused in the blending kernel.

    Args:
        target_image: [H, W, 3] float in [0, 1] or uint8.
        metric: "sad" (sum of absolute differences over RGB), "ssd", "psnr" (100 - PSNR) or "ncc"
            (1 - mean per-channel zero-mean normalised cross-correlation).
        mask_alpha: pixels whose rendered alpha is below this are ignored.

    Returns:
        float64 [B] (a float for a single pose).
    """
    from .costs import cost_from_stats

    _check(scene, camera)
    plist, single = as_pose_list(poses)
    img = np.asarray(target_image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    if img.shape != (camera.height, camera.width, 3):
        raise ValueError(f"target image must be [{camera.height}, {camera.width}, 3], got {img.shape}")
    r = get_renderer(scene, config)
    stats = r.cost_stats(camera, plist, r.upload_image(img), background, mask_alpha)
    cost = cost_from_stats(stats, metric, camera.width * camera.height)
    return float(cost[0]) if single else cost
