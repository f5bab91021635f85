"""The renderer: one scene's Gaussians resident on the Taichi device, rendered and scored in batches of poses.

All poses of one call go through each kernel stage in one launch (the batch is a leading dimension); a batch
larger than ``RasterConfig.max_batch_elements`` (poses x Gaussians) is split into chunks. Workspaces are reused
per image size, so repeated calls neither re-upload the scene nor recompile (kernels take ndarrays of any shape).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import taichi as ti

from ..core.backend import current_arch
from ..core.camera import Camera, pose_cameras, size_camera
from ..core.pose import Pose
from ..core.scene import GaussianScene
from ..kernels import RasterConfig, cull, splat, window
from ..kernels.blend import cost_kernel, image_func, image_kernel, reduce_kernel
from ..kernels.footprint import uses_ellipse_tiles
from ..kernels.launch import empty, launcher
from ..kernels.layout import Stat
from ..kernels.pose_grad import uses_masks
from ..kernels.projection import projection_kernel
from ..kernels.tile_sort import bin_parallel, tile_sort_kernel
from .buffers import ImageBuffers, Pool, StatBuffers, WindowBuffers, Workspace, blend_mode, read_rows, sort_mode
from .derivatives import PoseDerivatives
from .prepare import DeviceGaussians, upload

#: the share of the Gaussians from which a selection (a working set, a union of them) is rendered from the whole map
NEARLY_ALL = 0.95


class Renderer(PoseDerivatives):
    """One scene's Gaussians resident on the Taichi device (``RendererLike``).

    It holds no reference to the :class:`GaussianScene`, so a cache keyed by the scene (``get_renderer``) lets the
    scene go when its caller drops it. Poses are world-to-camera; images float32, costs float64.

    Example:
        >>> r = Renderer(scene)
        >>> rgb, alpha, depth = r.render_full(camera, [T1, T2])        # [2, H, W, 3], [2, H, W], [2, H, W]
    """

    MIN_WORKSPACE = 14  # poses: a search expansion's children (12 moves, a pattern move) fit

    def __init__(self, scene: GaussianScene, config: RasterConfig | None = None):
        config, arch = config or RasterConfig(), current_arch()
        self.blend_mode = mode = blend_mode(config.blend, arch)
        self.config = config.for_layout(mode == "splat" and arch != "cuda")  # the derivative pass's tile size
        if scene.num_gaussians == 0:
            raise ValueError("scene has no Gaussians")
        self.sh_degree = scene.sh_degree
        self.gaussians = DeviceGaussians.from_scene(scene)
        self.pool = Pool()
        self.sort_mode = sort_mode(self.config.sort, arch)
        self.ellipse_tiles = ellipse = uses_ellipse_tiles(self.config, arch)  # RasterConfig.tile_test
        # the projection, and its variant for cameras of reduced images (``Camera.downsample``; compiled on use)
        self._project, self._project_filtered = (launcher(projection_kernel(
            self.config, self.sh_degree, self.sort_mode == "serial", ellipse, filtered)) for filtered in (False, True))
        self._sort = launcher(tile_sort_kernel(self.config, ellipse))
        cost, img = (splat.splat_cost_kernel, splat.splat_image_func) if mode == "splat" else (cost_kernel, image_func)
        self._blend_cost, self._blend_image = launcher(cost(self.config)), launcher(image_kernel(img(self.config)))
        self._reduce = launcher(reduce_kernel())
        self.grad_masks = uses_masks(self.config, arch, mode == "splat")  # the derivative pass's masks
        self._root: Renderer | None = None  # for a subset: the renderer it was selected from, and its
        self._root_index: np.ndarray | None = None  # resident indices there (increasing)

    # ---- the Gaussians: subsets share this renderer's kernels and pool ----

    @property
    def n(self) -> int:
        """Resident Gaussians."""
        return self.gaussians.n

    #: ``RendererLike``'s selections made while rendering: none (its Gaussians are fixed)
    selections = 0

    @property
    def full(self) -> Renderer:
        """``RendererLike``'s renderer of the whole set this one renders from: itself (``largest``: ``n``)."""
        return self

    largest = n

    @property
    def source_index(self) -> np.ndarray:
        """[n]: scene index of each resident Gaussian (-1: none)."""
        return self.gaussians.source_index

    def with_gaussians(self, gaussians: DeviceGaussians) -> Renderer:
        """A renderer of other Gaussians with this one's config, compiled kernels and pool."""
        other = object.__new__(Renderer)
        other.__dict__.update(self.__dict__)
        other.gaussians, other._root, other._root_index = gaussians, None, None
        return other

    @property
    def root(self) -> Renderer:
        """The renderer this one's Gaussians were selected from (:meth:`subset`, :meth:`working_set`; itself when
        it is not a subset)."""
        return self._root if self._root is not None else self

    def union(self, renderers: Sequence[Renderer]) -> Renderer:
        """A renderer of the union of ``renderers``' Gaussians, all subsets of this one (or this one), in resident
        order: where each of them renders a pose bit for bit as this one does (a working set's region), so does
        the union (it keeps every Gaussian they keep, in the same order). This one when any of them is, or when
        the union holds nearly all Gaussians."""
        if any(r.root is not self for r in renderers):
            raise ValueError("union: every renderer must be a subset of this one")
        if any(r is self for r in renderers):
            return self
        return self._selection(functools.reduce(np.union1d, [r._root_index for r in renderers]).astype(np.int32))

    def working_set(self, cameras: Sequence[Camera], pose: Pose, max_shift: float, max_rotation_deg: float
                    ) -> Renderer:
        """A renderer of the Gaussians that some pose of a region can see (``kernels/cull.py``).

        Args:
            cameras: every camera (size, intrinsics) the caller will render with.
            pose: the region's centre pose (world-to-camera).
            max_shift / max_rotation_deg: camera-centre shift (scene units) and rotation (degrees) bounding it.

        Returns:
            A renderer of the kept Gaussians (same order; on the device, only the index list crosses), or ``self``
            when nearly all are kept (or none). Its images and costs equal this renderer's bit for bit for every
            pose of the region.
        """
        g = self.gaussians
        rows, fac = cull.planes(cameras, self.config)
        keep = empty(ti.i32, (self.n,))  # the kernel sets every entry
        planes = [upload(np.asarray(a, np.float64), ti.f64) for a in (pose.matrix34(), rows, fac)]
        launcher(cull.keep_kernel(self.config))(g.means, g.smax, g.opacities, *planes, float(max_shift),
                                                float(np.radians(max_rotation_deg)), keep)
        return self._selection(np.flatnonzero(read_rows(keep, self.n)).astype(np.int32))

    def _selection(self, idx: np.ndarray) -> Renderer:
        """A renderer of the resident Gaussians ``idx`` [M] (increasing), or this one when they are nearly all
        (``NEARLY_ALL`` of them) or none: a subset pays only where it drops a good share."""
        return self if idx.size >= NEARLY_ALL * self.n or idx.size == 0 else self.subset(idx)

    def subset(self, idx: np.ndarray) -> Renderer:
        """A renderer of the resident Gaussians ``idx`` [M] (increasing resident indices), gathered on the
        device; its ``source_index`` maps them to the scene."""
        idx = np.asarray(idx, np.int32)
        if idx.ndim != 1 or idx.size == 0 or np.any(np.diff(idx) <= 0) or idx[0] < 0 or idx[-1] >= self.n:
            raise ValueError("subset indices must be a non-empty increasing list of Gaussian indices")
        nd_idx = upload(idx, ti.i32)
        gathered = {}
        for name in DeviceGaussians.FIELDS:
            src = getattr(self.gaussians, name)
            dst = empty(ti.f32, (idx.size,) + tuple(src.shape[1:]))
            launcher(cull.gather_kernel(len(src.shape)))(src, nd_idx, dst)
            gathered[name] = dst
        other = self.with_gaussians(DeviceGaussians(**gathered, source_index=self.source_index[idx]))
        other._root = self.root
        other._root_index = idx if self._root_index is None else self._root_index[idx]
        return other

    def arrays(self) -> dict[str, np.ndarray]:
        """Host copies of the resident Gaussians, in resident order: ``means`` [n, 3], ``cov3d`` [n, 6]
        (xx, xy, xz, yy, yz, zz), ``opacities`` [n], ``sh`` [n, K, 3], ``smax`` [n] (bound on the std. dev.)."""
        return self.gaussians.to_arrays()

    def derived(self, arrays: dict[str, np.ndarray], source_index: np.ndarray) -> Renderer:
        """A renderer of other Gaussians (``arrays`` as from :meth:`arrays`, resident in the order given) with
        this one's config, kernels and pool; ``source_index`` [m]: scene index per Gaussian (-1: none)."""
        if len(arrays["means"]) == 0:
            raise ValueError("no Gaussians")
        return self.with_gaussians(DeviceGaussians.from_arrays(arrays, source_index))

    # ---- workspaces and geometry (projection + tile sort) ----

    @property
    def chunk(self) -> int:
        """Poses per launch."""
        return max(1, self.config.max_batch_elements // self.n)

    def _chunks(self, camera: Camera | Sequence[Camera], poses: list[Pose], size: int | None = None):
        """(cameras, poses) of consecutive parts of at most ``size`` (default: ``chunk``) poses, a camera per pose
        (:func:`pose_cameras`)."""
        cams = pose_cameras(camera, len(poses))
        c = size or self.chunk
        for s in range(0, len(poses), c):
            yield cams[s:s + c], poses[s:s + c]

    def _query_parts(self, camera: Camera | Sequence[Camera], poses: list[Pose], query_index,
                     size: int | None = None):
        """(cameras, poses, device query slots) of consecutive parts of at most ``size`` (default: ``chunk``)
        poses; ``query_index`` [B] (None: every pose against slot 0)."""
        qi = np.zeros(len(poses), np.int32) if query_index is None else np.asarray(query_index, np.int32)
        if qi.shape != (len(poses),):
            raise ValueError(f"query_index must be [{len(poses)}] (one slot per pose), got {qi.shape}")
        c = size or self.chunk
        for (cams, part), s in zip(self._chunks(camera, poses, c), range(0, len(poses), c)):
            yield cams, part, self.pool.query_index(qi[s:s + c])

    def workspace(self, camera: Camera, batch: int, grad: bool = False) -> Workspace:
        """The buffers for up to ``batch`` poses at ``camera``'s size and tiling (``grad``: the derivative pass's,
        ``RasterConfig.grad_tile_size``): one per size, reused by every call that fits and grown when one needs
        more (re-allocating per batch size cost more than the renders of a search expansion)."""
        ts = self.config.grad_tile_size if grad else self.config.tile_size
        key = (camera.width, camera.height, ts)
        ws = self.pool.workspaces.get(key)
        if ws is None or ws.batch < batch:
            B = max(batch, min(self.chunk, self.MIN_WORKSPACE), ws.batch if ws is not None else 0)
            ws = Workspace.allocate(B, camera.width, camera.height, ts, self.sort_mode == "parallel")
            self.pool.workspaces[key] = ws
        self.pool.projection_records(ws.batch, self.n, self.sort_mode == "parallel")
        return ws

    def _geometry(self, camera: Camera | Sequence[Camera], poses: list[Pose], ws: Workspace, background) -> None:
        """Projection and tile sort for up to ``ws.batch`` poses (``camera``: one, or one per pose of one size),
        binned at the workspace's tile size, into the pool's records and tile lists."""
        B = len(poses)
        cams = pose_cameras(camera, B)
        rec = self.pool.records
        g = self.gaussians
        vm = np.zeros((ws.batch, 4, 4), np.float32)
        for k, T in enumerate(poses):
            vm[k, :3] = T.matrix34()
            vm[k, 3, :3] = T.centre()
        ws.upload("viewmats", vm)
        # every row of the workspace filled (rows past the last pose repeat the first camera), so that calls of
        # one camera with any number of poses upload the same bytes: once per query, not once per batch size
        distinct = list(dict.fromkeys(cams))
        rows = {c: ([c.fx, c.fy, c.cx, c.cy, *self.config.widening(c.downsample)],
                    [cull.extent_coefficient(*cull.jacobian_limits(c)),
                     cull.extent_pixels(self.config, c.downsample) / min(c.fx, c.fy)]) for c in distinct}
        intrin = np.tile(np.array(rows[cams[0]][0], np.float32), (ws.batch, 1))
        extent = np.tile(np.array(rows[cams[0]][1], np.float32), (ws.batch, 1))
        if len(distinct) > 1:
            for k, c in enumerate(cams):
                intrin[k], extent[k] = rows[c]
        ws.upload("intrin", intrin)
        ws.upload("extent", extent)
        camera = cams[0]  # the image size
        ws.upload("background", np.asarray(background, np.float32).reshape(3))
        tx, ty = ws.tiles
        parallel = self.sort_mode == "parallel"
        # the serial sort's totals: counted by the projection into a host array, back with its launch
        totals = self.pool.placeholder(ti.i64) if parallel else np.zeros(B, np.int64)
        project = self._project_filtered if any(c.downsample != 1.0 for c in distinct) else self._project
        project(g.means, g.cov3d, g.opacities, g.sh, g.smax, ws.viewmats, ws.intrin, camera.width, camera.height,
                ws.tile, B, ws.extent, ws.cams, rec.depth, rec.rect, rec.ntiles, rec.packed, totals)
        if parallel:
            totals = bin_parallel(rec.depth, rec.rect, rec.ntiles, rec.offsets, B, self.n, tx, tx * ty,
                                  lambda m: self.pool.tile_lists(m, parallel=True), self.pool.radix_scratch(),
                                  ws.tile_start, ws.tile_counts, self.ellipse_tiles)
        base = np.zeros(ws.batch, np.int64)
        base[1:B] = np.cumsum(totals)[:-1]
        ws.upload("isect_base", base)
        if not parallel:
            isect = self.pool.tile_lists(int(totals.sum()), parallel=False).isect
            self._sort(rec.depth, rec.rect, rec.ntiles, ws.isect_base, tx, ty, B, self.n, rec.keys, rec.boxes,
                       ws.cursor, ws.tile_start, isect)

    # ---- images and costs ----

    def _images_ready(self, cams: list[Camera], part: list[Pose], background, batch: int
                      ) -> tuple[Workspace, tuple]:
        """Geometry of up to one chunk of poses (a camera each, one size), into a workspace whose image buffers
        exist (``ws.images``), and the arguments an image blend starts with (``blend.image_func``'s, up to the
        number of poses). ``batch``: the workspace size (poses of the whole call, capped at one chunk)."""
        camera = cams[0]
        ws = self.workspace(camera, batch)
        if ws.images is None:
            ws.images = ImageBuffers.allocate(ws.batch, camera.height, camera.width)
        self._geometry(cams, part, ws, background)
        tx, ty = ws.tiles
        return ws, (self.pool.records.packed, ws.tile_start, self.pool.lists.isect, ws.isect_base, ws.background,
                    tx, ty, len(part))

    def visible(self, camera: Camera | Sequence[Camera], poses: list[Pose]) -> np.ndarray:
        """Which Gaussians the projection keeps (touch at least one tile) for each pose: bool [B, n], in the
        order of ``source_index`` (scene indices)."""
        out = []
        for cams, part in self._chunks(camera, poses):
            ws = self.workspace(cams[0], min(len(poses), self.chunk))
            self._geometry(cams, part, ws, (0.0, 0.0, 0.0))
            out.append(read_rows(self.pool.records.ntiles, len(part)) > 0)
        return np.concatenate(out)

    def render_full(self, camera: Camera | Sequence[Camera], poses: list[Pose], background=(0.0, 0.0, 0.0)):
        """Colour [B, H, W, 3], alpha [B, H, W] and accumulated depth [B, H, W] (float32 numpy). ``camera``: one,
        or one per pose (one image size; so for every method here)."""
        rgbs, alphas, depths = [], [], []
        for cams, part in self._chunks(camera, poses):
            ws, head = self._images_ready(cams, part, background, min(len(poses), self.chunk))
            im = ws.images
            self._blend_image(*head, im.rgb, im.alpha, im.dimg)
            n = len(part)
            rgbs.append(read_rows(im.rgb, n))
            alphas.append(read_rows(im.alpha, n))
            depths.append(read_rows(im.dimg, n))
        return np.concatenate(rgbs), np.concatenate(alphas), np.concatenate(depths)

    @staticmethod
    def upload_image(image: np.ndarray) -> ti.Ndarray:
        """A comparison image [H, W, 3] (float32 in [0, 1]) on the device, for :meth:`cost_stats`."""
        image = np.ascontiguousarray(image, dtype=np.float32)
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"comparison image must be [H, W, 3], got {image.shape}")
        return upload(image, ti.f32)

    @staticmethod
    def upload_window_query(image: np.ndarray) -> ti.Ndarray:
        """Query statistics for :meth:`window_cost`: windowed mean and variance per channel, on the device
        ([1, H, W, 3, window.NQ]: one query; ``image`` [H, W, 3] float in [0, 1])."""
        q = Renderer.upload_image(image)
        out = empty(ti.f32, (1, *q.shape[:2], 3, window.NQ))  # the kernel sets every entry (and tmp's)
        launcher(window.query_stats_kernel())(q, 0, empty(ti.f32, (*q.shape[:2], 3, 2)), out)
        return out

    @staticmethod
    def stack_window_queries(stats: Sequence[ti.Ndarray], out: ti.Ndarray | None = None, slots=None) -> ti.Ndarray:
        """Query statistics of one size (each from :meth:`upload_window_query`) stacked on the device, query ``k`` in
        slot ``slots[k]`` (default ``k``) of ``out`` [Q, H, W, 3, window.NQ] (default: a new array of ``len(stats)``
        slots), for one launch scoring the poses of many queries; returns ``out``."""
        shapes = {tuple(q.shape[1:]) for q in stats} | ({tuple(out.shape[1:])} if out is not None else set())
        if len(shapes) != 1 or any(q.shape[0] != 1 for q in stats):
            raise ValueError(f"stacked queries must be single queries of one size, got {[q.shape for q in stats]}")
        out = empty(ti.f32, (len(stats),) + shapes.pop()) if out is None else out
        copy = launcher(window.copy_query_kernel())
        for k, q in zip(range(len(stats)) if slots is None else slots, stats):
            copy(q, 0, out, int(k))
        return out

    def window_cost(self, camera: Camera | Sequence[Camera], poses: list[Pose], qstats: ti.Ndarray,
                    background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0, luminance: bool = False,
                    query_index=None) -> np.ndarray:
        """Windowed structural similarity of each pose's rendering with the query: [B, 2] float64, the sum over
        valid pixels of the per-pixel value (``cs``, or full SSIM when ``luminance``) and the valid pixel count.

        Args:
            qstats: from :meth:`upload_window_query` (or :meth:`stack_window_queries`), at the camera's size.
            query_index: [B] each pose's query slot in ``qstats`` (default: all 0). A pose's numbers do not depend
                on the other poses of the call.
        """
        _check_query_size(qstats, camera)
        out = []
        for cams, part, qi in self._query_parts(camera, poses, query_index):
            ws, head = self._images_ready(cams, part, background, min(len(poses), self.chunk))
            im = ws.images
            if ws.window is None:
                ws.window = WindowBuffers.allocate(ws.batch, cams[0].height, cams[0].width)
            sums = np.empty((len(part), 2), np.float64)
            launcher(window.window_cost_kernel(self.config, self.blend_mode == "splat", bool(luminance)))(
                *head, im.rgb, im.alpha, im.dimg, qstats, qi, float(mask_alpha), ws.window.h, ws.window.rows, sums)
            out.append(sums)
        return np.concatenate(out)

    def cost_stats(self, camera: Camera | Sequence[Camera], poses: list[Pose], target: ti.Ndarray,
                   background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0) -> np.ndarray:
        """Photometric statistics of each pose's rendering against ``target`` (the comparison image from
        :meth:`upload_image`, at the camera's size): [B, Stat.SIZE] float64 (``kernels.layout.Stat``: n_valid,
        SAD, SSD, per-channel sums)."""
        size = size_camera(camera)
        if size is not None and tuple(target.shape) != (size.height, size.width, 3):
            raise ValueError(f"comparison image is {tuple(target.shape)}, camera needs "
                             f"({size.height}, {size.width}, 3)")
        out = []
        for cams, part in self._chunks(camera, poses):
            ws = self.workspace(cams[0], min(len(poses), self.chunk))
            tx, ty = ws.tiles
            if ws.stats is None:
                rows = ty if self.blend_mode == "splat" else cams[0].height
                ws.stats = StatBuffers(ti.ndarray(ti.f32, (ws.batch, rows, tx, Stat.SIZE)))
            self._geometry(cams, part, ws, background)
            head = (self.pool.records.packed, ws.tile_start, self.pool.lists.isect, ws.isect_base, ws.background, tx)
            if self.blend_mode == "splat":
                self._blend_cost(*head, ty, len(part), target, float(mask_alpha), ws.stats.runs)
            else:
                self._blend_cost(*head, len(part), target, float(mask_alpha), ws.stats.runs)
            stats = np.empty((len(part), Stat.SIZE), np.float64)  # a host array: back with the launch
            self._reduce(ws.stats.runs, len(part), stats)
            out.append(stats)
        return np.concatenate(out)

    # ---- pose derivatives (the rest in ``render/derivatives.py``) ----

    def pose_gradient(self, camera: Camera | Sequence[Camera], poses: list[Pose], qstats: ti.Ndarray,
                      background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0, query_index=None):
        """The ``cs`` cost of each pose, its gradient and its Gauss-Newton Hessian in ``xi = (w, v)``: cost [B],
        grad [B, 6], JtJ [B, 6, 6] (float64); no image leaves the device. ``qstats``, ``query_index``: as for
        :meth:`window_cost`; the cost equals :meth:`window_cost`'s ``1 - mean``. (``render_derivatives`` and
        ``pose_gradient_noise`` are ``PoseDerivatives``'.)"""
        _check_query_size(qstats, camera)
        return self.cs_gradient(camera, poses, qstats, background, mask_alpha, query_index)


def _check_query_size(qstats, camera: Camera | Sequence[Camera]) -> None:
    camera = size_camera(camera)
    if camera is not None and (len(qstats.shape) != 5 or tuple(qstats.shape[1:3]) != (camera.height, camera.width)):
        raise ValueError(f"query statistics are {tuple(qstats.shape)}, camera needs "
                         f"(Q, {camera.height}, {camera.width}, 3, {window.NQ})")
