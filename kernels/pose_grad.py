"""Forward-mode derivatives of the rendering with respect to the camera pose.

Pose increment ``xi = (w, v)`` [6] (rotation vector, then translation): a left perturbation in the camera frame,

    R' = Exp(w) R,   t' = Exp(w) t + v,   so   p_c' = p_c + w x p_c + v + O(|xi|^2)

(the axes of the search's lattice, turning about the camera centre). ``hgsloc_plugin.pose_update`` applies it.

Three steps, run in turn by one launch (:func:`derivative_images_kernel`) after the projection and tile sort of the
same poses (they read its ``packed`` records, ``ntiles`` and tile lists):

- ``projection_grad``: per pose and kept Gaussian, the derivatives of the 2D mean (mx, my) and the conic
  (a, b, c) along the six axes: ``dpacked [B, N, 5 * 6]`` (quantity-major, ``DX, DY, DCA, DCB, DCC``).
  The chain: ``dp_c = w x p_c + v``; mean ``m = f p/z + c``; camera covariance ``Sc = R S R^T`` turns with the
  rotation, ``dSc = [w]x Sc - Sc [w]x``; the projection Jacobian ``J(p_c)`` with the same clamp of the off-axis
  term as the forward pass (a clamped coordinate follows z only); ``cov2 = J Sc J^T + eps2d I``;
  conic ``Q = cov2^-1``, ``dQ = -Q dcov2 Q``. The SH colour's view direction is held fixed (it changes with the
  camera centre only; measured in ``tests/test_pose_grad.py``: 1.6-2.7 % (relative L2) of the translation
  derivatives on the SH-3 scene, none of the rotation ones; the polish converges regardless).
- the derivative blend (``blend_grad.py``): front-to-back compositing carrying the derivatives, one task per
  tile on the CPU (``splat_grad``), one per pixel on CUDA (``blend_grad``); output colour, alpha and
  ``drgb`` [B, H, W, 3 * 6].
- ``pixel_masks`` (between the two, for the per-pixel layout where used; tiles of at most 8 x 8 pixels): per
  tile-list entry, a 64-bit mask of the tile's pixels its Gaussian may reach. A pixel walks its tile's whole list,
  most of whose Gaussians miss it (snow, 99 px: 426 entries walked per pixel, 45 contributing); with the mask it
  skips them on one bit test instead of loading and evaluating the record. The mask is a superset of the pixels
  the exact test keeps, so every number is unchanged (``tests/test_pose_grad.py``).
Reference twin: ``tests/test_pose_grad.py`` (finite differences of ``tests/reference/render_torch.py`` in float64).
"""

import functools

import taichi as ti

from .blend import tile_range
from .blend_grad import DCA, DCB, DCC, DX, DY, NXI, blend_grad_func, splat_grad_func
from .config import RasterConfig
from .footprint import PIXEL_MARGIN, SIGMA_MARGIN
from .grain import item, spread
from .layout import Cam
from .projection import camera_covariance, clamped_jacobian, view_rt
from .splat import ellipse_of, tile_pixels

NDER = 5 * NXI
MASK_BITS = 64  # pixels of a tile a ``pixel_masks`` entry can describe (tiles of at most 8 x 8)


def uses_masks(config: RasterConfig, arch: str, splat: bool) -> bool:
    """Whether the derivative pass runs ``pixel_masks`` on backend ``arch`` (``RasterConfig.grad_masks``; "auto":
    on the CPU, when the tiles are small enough for one bit per pixel); never for the ``splat`` layout, which
    visits each Gaussian's pixels only."""
    if splat:
        return False
    if config.grad_masks == "auto":
        return arch != "cuda" and config.grad_tile(False) ** 2 <= MASK_BITS
    return config.grad_masks == "on"


@functools.cache
def projection_grad_func(config: RasterConfig):
    """``projection_grad`` (a ti.func: one parallel loop).

    Arguments:
        means [N, 3], cov3d [N, 6], viewmats [B, 4, 4] (``projection.view_rt``), cams [B, Cam.SIZE] (each pose's
        camera record from the projection, ``layout.Cam``), num_poses, ntiles [B, N] (from the projection: 0 =
        culled, skipped);
        output: dpacked [B, N, NDER].
    """
    eps2d = config.eps2d

    @ti.func
    def projection_grad(
        means: ti.template(),
        cov3d: ti.template(),
        viewmats: ti.template(),
        cams: ti.template(),
        num_poses,
        ntiles: ti.template(),
        dpacked: ti.template(),
    ):
        n = means.shape[0]
        for b, i in ti.ndrange(num_poses, n):
            if ntiles[b, i] == 0:
                continue
            fx = cams[b, Cam.FX]
            fy = cams[b, Cam.FY]
            R, t = view_rt(viewmats, b)
            p = R @ ti.Vector([means[i, 0], means[i, 1], means[i, 2]]) + t
            Sc = camera_covariance(cov3d, i, R)
            J, ux, vy = clamped_jacobian(p, fx, fy, cams[b, Cam.LIM_X_POS], cams[b, Cam.LIM_X_NEG],
                                         cams[b, Cam.LIM_Y_POS], cams[b, Cam.LIM_Y_NEG])
            z = p[2]
            rz = 1.0 / z
            free_x = 1.0 if ux == p[0] * rz else 0.0  # unclamped: tx = x; clamped: tx = z * limit
            free_y = 1.0 if vy == p[1] * rz else 0.0
            tx = z * ux
            ty = z * vy
            cov2 = J @ Sc @ J.transpose()
            c00 = cov2[0, 0] + eps2d
            c01 = cov2[0, 1]
            c11 = cov2[1, 1] + eps2d
            inv_det = 1.0 / (c00 * c11 - c01 * c01)
            Q = ti.Matrix([[c11 * inv_det, -c01 * inv_det], [-c01 * inv_det, c00 * inv_det]])
            JS = J @ Sc
            for k in range(NXI):  # a run-time loop: one copy of the body (loading time), exact 0/1 increments
                w = ti.Vector([ti.select(k == 0, 1.0, 0.0), ti.select(k == 1, 1.0, 0.0), ti.select(k == 2, 1.0, 0.0)])
                Wk = ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])  # [w]x
                dp = Wk @ p + ti.Vector([ti.select(k == 3, 1.0, 0.0), ti.select(k == 4, 1.0, 0.0),
                                         ti.select(k == 5, 1.0, 0.0)])
                dSc = Wk @ Sc - Sc @ Wk
                dz = dp[2]
                drz = -dz * rz * rz
                dtx = free_x * dp[0] + (1.0 - free_x) * ux * dz
                dty = free_y * dp[1] + (1.0 - free_y) * vy * dz
                dJ = ti.Matrix([[fx * drz, 0.0, -fx * (dtx * rz * rz + 2.0 * tx * rz * drz)],
                                [0.0, fy * drz, -fy * (dty * rz * rz + 2.0 * ty * rz * drz)]])
                dcov = dJ @ JS.transpose() + J @ dSc @ J.transpose() + JS @ dJ.transpose()
                dQ = -(Q @ dcov @ Q)
                dpacked[b, i, DX * NXI + k] = fx * (dp[0] * rz + p[0] * drz)
                dpacked[b, i, DY * NXI + k] = fy * (dp[1] * rz + p[1] * drz)
                dpacked[b, i, DCA * NXI + k] = dQ[0, 0]
                dpacked[b, i, DCB * NXI + k] = dQ[0, 1]
                dpacked[b, i, DCC * NXI + k] = dQ[1, 1]

    return projection_grad


@functools.cache
def pixel_masks_func(config: RasterConfig):
    """``pixel_masks`` (a ti.func: one task per pose and tile; ``config.grad_tile_size`` <= 8).

    Arguments:
        packed [B, N, Rec.SIZE], tile_start [B, T + 1], isect [M], isect_base [B]: the projection's records and
        the tile lists binned at ``config.grad_tile_size``; tiles_x, tiles_y, num_poses, width, height;
        output: masks [>= M] u64, entry k's bit ``(py - y0) * tile + (px - x0)`` set for each pixel of its tile
        (first pixel x0, y0) inside the ellipse ``sigma <= LIM + SIGMA_MARGIN`` widened by ``PIXEL_MARGIN`` per
        side: every pixel whose alpha reaches ``alpha_min``, and a few more.
    """
    tile = config.grad_tile_size

    @ti.func
    def pixel_masks(
        packed: ti.template(),
        tile_start: ti.template(),
        isect: ti.template(),
        isect_base: ti.template(),
        tiles_x,
        tiles_y,
        num_poses,
        width,
        height,
        masks: ti.template(),
    ):
        stride = ti.static(spread())  # one task per tile on the CPU (grain.py)
        nt = tiles_x * tiles_y
        for task in range(num_poses * nt * stride):
            is_item, b, t = item(task, stride, nt)
            if is_item:
                x0, y0, x1, y1, _ = tile_pixels(t, tiles_x, tile, width, height)
                start, end = tile_range(b, t, tile_start, isect_base)
                for k in range(start, end):
                    g = isect[k]
                    mx, my, ca, cb, cc, lim = ellipse_of(packed, b, g)
                    lim += SIGMA_MARGIN
                    inv_ca = 1.0 / ca
                    m = ti.u64(0)
                    for py in range(y0, y1):
                        # sigma = 0.5 ca dx^2 + (cb dy) dx + 0.5 cc dy^2 <= lim, dx = mx - (px + 0.5)
                        dy = my - (ti.cast(py, ti.f32) + 0.5)
                        bq = cb * dy
                        disc = bq * bq - ca * (cc * dy * dy - 2.0 * lim)
                        if disc >= 0.0:
                            sq = ti.sqrt(disc)
                            lo = mx - 0.5 - PIXEL_MARGIN - (sq - bq) * inv_ca  # px >= lo
                            hi = mx - 0.5 + PIXEL_MARGIN + (sq + bq) * inv_ca  # px <= hi
                            lx = ti.max(x0, ti.cast(ti.floor(lo), ti.i32))
                            hx = ti.min(x1, ti.cast(ti.floor(hi), ti.i32) + 1)
                            if hx > lx:  # bits lx - x0 .. hx - x0 - 1 of the row's (at most 8 pixels)
                                run = (ti.u64(1) << ti.cast(hx - lx, ti.u64)) - ti.u64(1)
                                m |= run << ti.cast((py - y0) * tile + lx - x0, ti.u64)
                    masks[k] = m

    return pixel_masks


@functools.cache
def derivative_images_kernel(config: RasterConfig, splat: bool, masked: bool):
    """The derivative pass after the projection and tile sort of the same poses, in one launch: the records'
    derivatives (``projection_grad``, each pose with its camera record from the projection's ``cams``), with
    ``masked`` the pixel masks (``pixel_masks``), then the colour, alpha and colour derivatives (``splat_grad``
    with ``splat``, else ``blend_grad``). Arguments: those of the three, in that order, each once."""
    if splat and masked:
        raise ValueError("the pixel masks serve the per-pixel derivative blend only")
    records, masks_of = projection_grad_func(config), pixel_masks_func(config)
    blend = splat_grad_func(config) if splat else blend_grad_func(config, masked)
    f32, i32 = ti.f32, ti.i32

    @ti.kernel
    def derivative_images(
        means: ti.types.ndarray(dtype=f32, ndim=2),
        cov3d: ti.types.ndarray(dtype=f32, ndim=2),
        viewmats: ti.types.ndarray(dtype=f32, ndim=3),
        cams: ti.types.ndarray(dtype=f32, ndim=2),
        width: i32,
        height: i32,
        num_poses: i32,
        ntiles: ti.types.ndarray(dtype=i32, ndim=2),
        dpacked: ti.types.ndarray(dtype=f32, ndim=3),
        packed: ti.types.ndarray(dtype=f32, ndim=3),
        tile_start: ti.types.ndarray(dtype=i32, ndim=2),
        isect: ti.types.ndarray(dtype=i32, ndim=1),
        isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
        masks: ti.types.ndarray(dtype=ti.u64, ndim=1),
        background: ti.types.ndarray(dtype=f32, ndim=1),
        tiles_x: i32,
        tiles_y: i32,
        out_rgb: ti.types.ndarray(dtype=f32, ndim=4),
        out_alpha: ti.types.ndarray(dtype=f32, ndim=3),
        out_d: ti.types.ndarray(dtype=f32, ndim=4),
    ):
        records(means, cov3d, viewmats, cams, num_poses, ntiles, dpacked)
        if ti.static(masked):
            masks_of(packed, tile_start, isect, isect_base, tiles_x, tiles_y, num_poses, width, height, masks)
        blend(packed, dpacked, tile_start, isect, isect_base, masks, background, tiles_x, tiles_y, num_poses, out_rgb,
              out_alpha, out_d)

    return derivative_images
