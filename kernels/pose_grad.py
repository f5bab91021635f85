"""Forward-mode derivatives of the rendering with respect to the camera pose.

Pose increment ``xi = (w, v)`` [6] (rotation vector, then translation): a left perturbation in the camera frame,

    R' = Exp(w) R,   t' = Exp(w) t + v,   so   p_c' = p_c + w x p_c + v + O(|xi|^2)

(the axes of the search's lattice, turning about the camera centre). ``Pose.perturbed_in_camera`` applies it.

Three steps, run in turn by one launch (:func:`derivative_images_kernel`) after the projection and tile sort of the
same poses (they read its ``packed`` records, ``ntiles`` and tile lists):

- ``projection_grad``: per pose and kept Gaussian, the derivatives of the 2D mean (mx, my) and the conic
  (a, b, c) along the six axes: ``dpacked [B, N, 5 * 6]`` (quantity-major, ``DX, DY, DCA, DCB, DCC``).
  The chain: ``dp_c = w x p_c + v``; mean ``m = f p/z + c``; camera covariance ``Sc = R S R^T`` turns with the
  rotation, ``dSc = [w]x Sc - Sc [w]x``; the projection Jacobian ``J(p_c)`` with the same clamp of the off-axis
  term as the forward pass (a clamped coordinate follows z only); ``cov2 = J Sc J^T + e I`` (``e``: the camera's
  dilation and filter, ``RasterConfig.widening``; a filter's opacity compensation is held fixed), so with
  ``JS = J Sc`` and ``N = dJ + J [w]x``, ``dcov2 = N JS^T + JS N^T`` (2 x 3 products per axis, no 3 x 3 ones);
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


@ti.func
def _rotated(k: ti.template(), p):
    """dp_c along axis ``k`` of ``xi``: ``e_k x p`` for the rotation (k < 3), ``e_(k-3)`` for the translation."""
    out = ti.Vector([0.0, 0.0, 0.0])
    if ti.static(k == 0):
        out = ti.Vector([0.0, -p[2], p[1]])
    elif ti.static(k == 1):
        out = ti.Vector([p[2], 0.0, -p[0]])
    elif ti.static(k == 2):
        out = ti.Vector([-p[1], p[0], 0.0])
    else:
        out[k - 3] = 1.0
    return out


@ti.func
def _turned(k: ti.template(), J):
    """``J [e_k]x`` [2, 3] for the rotation axes (k < 3: column m is ``J (e_k x e_m)``), 0 for the translation."""
    out = ti.Matrix([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    if ti.static(k == 0):
        out = ti.Matrix([[0.0, J[0, 2], -J[0, 1]], [0.0, J[1, 2], -J[1, 1]]])
    elif ti.static(k == 1):
        out = ti.Matrix([[-J[0, 2], 0.0, J[0, 0]], [-J[1, 2], 0.0, J[1, 0]]])
    elif ti.static(k == 2):
        out = ti.Matrix([[J[0, 1], -J[0, 0], 0.0], [J[1, 1], -J[1, 0], 0.0]])
    return out


@functools.cache
def projection_grad_func(config: RasterConfig):
    """``projection_grad`` (a ti.func: one parallel loop).

    Arguments:
        means [N, 3], cov3d [N, 6], viewmats [B, 4, 4] (``projection.view_rt``), cams [B, Cam.SIZE] (each pose's
        camera record from the projection, ``layout.Cam``), num_poses, ntiles [B, N] (from the projection: 0 =
        culled, skipped);
        output: dpacked [B, N, NDER].
    """

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
            widen = cams[b, Cam.DILATION] + cams[b, Cam.FILTER]
            c00 = cov2[0, 0] + widen
            c01 = cov2[0, 1]
            c11 = cov2[1, 1] + widen
            inv_det = 1.0 / (c00 * c11 - c01 * c01)
            Q = ti.Matrix([[c11 * inv_det, -c01 * inv_det], [-c01 * inv_det, c00 * inv_det]])
            JS = J @ Sc  # cov2 = JS J^T
            q00 = Q[0, 0]
            q01 = Q[0, 1]
            q11 = Q[1, 1]
            for k in ti.static(range(NXI)):
                dp = _rotated(k, p)  # w x p (k < 3), else the unit translation
                dz = dp[2]
                drz = -dz * rz * rz
                dtx = free_x * dp[0] + (1.0 - free_x) * ux * dz
                dty = free_y * dp[1] + (1.0 - free_y) * vy * dz
                # dcov = N JS^T + JS N^T with N = dJ + J [w]x (J dSc J^T = J [w]x JS^T + JS (J [w]x)^T)
                N = _turned(k, J) + ti.Matrix([[fx * drz, 0.0, -fx * (dtx * rz * rz + 2.0 * tx * rz * drz)],
                                               [0.0, fy * drz, -fy * (dty * rz * rz + 2.0 * ty * rz * drz)]])
                d00 = 2.0 * (N[0, 0] * JS[0, 0] + N[0, 1] * JS[0, 1] + N[0, 2] * JS[0, 2])
                d01 = (N[0, 0] * JS[1, 0] + N[0, 1] * JS[1, 1] + N[0, 2] * JS[1, 2]
                       + N[1, 0] * JS[0, 0] + N[1, 1] * JS[0, 1] + N[1, 2] * JS[0, 2])
                d11 = 2.0 * (N[1, 0] * JS[1, 0] + N[1, 1] * JS[1, 1] + N[1, 2] * JS[1, 2])
                e00 = q00 * d00 + q01 * d01  # (Q dcov) row 0 and row 1; dQ = -(Q dcov) Q, symmetric
                e01 = q00 * d01 + q01 * d11
                e10 = q01 * d00 + q11 * d01
                e11 = q01 * d01 + q11 * d11
                dpacked[b, i, DX * NXI + k] = fx * (dp[0] * rz + p[0] * drz)
                dpacked[b, i, DY * NXI + k] = fy * (dp[1] * rz + p[1] * drz)
                dpacked[b, i, DCA * NXI + k] = -(e00 * q00 + e01 * q01)
                dpacked[b, i, DCB * NXI + k] = -(e00 * q01 + e01 * q11)
                dpacked[b, i, DCC * NXI + k] = -(e10 * q01 + e11 * q11)

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
