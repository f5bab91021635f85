"""Projection kernel: world -> camera -> pixels, EWA 2D covariance, culling, SH colour, tile rectangles.

Mirrors gsplat 1.5.3 ``ProjectionEWA3DGSFused.cu`` (CONVENTIONS §6 steps 2-6); reference twin:
``tests/reference/render_torch.py::project``.
"""


import functools
import math

import taichi as ti

from .config import RasterConfig
from .footprint import box_tile_mask, write_mask
from .layout import Cam, Rec
from .sh import make_sh_func
from .tile_sort import count_tiles


@ti.func
def jacobian_clamps(fx, fy, cx, cy, wf, hf):
    """Limits of x / z and y / z in the projection Jacobian (image bounds plus 0.3 of the half field of view):
    (x_pos, x_neg, y_pos, y_neg)."""
    tan_fovx = 0.5 * wf / fx
    tan_fovy = 0.5 * hf / fy
    return ((wf - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx, (hf - cy) / fy + 0.3 * tan_fovy,
            cy / fy + 0.3 * tan_fovy)


@ti.func
def camera_records(intrin: ti.template(), extent: ti.template(), wf, hf, num_poses, cams: ti.template()):
    """Each pose's camera record cams [B, Cam.SIZE] (``layout.Cam``) from its intrinsics intrin [B, 6] (fx, fy,
    cx, cy, then the widening's dilation and filter: ``RasterConfig.widening``) and extent coefficients extent
    [B, 2], for images of wf x hf pixels (one loop: a task of its own)."""
    for b in range(num_poses):
        fx, fy, cx, cy = intrin[b, 0], intrin[b, 1], intrin[b, 2], intrin[b, 3]
        cams[b, Cam.DILATION] = intrin[b, 4]
        cams[b, Cam.FILTER] = intrin[b, 5]
        lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg = jacobian_clamps(fx, fy, cx, cy, wf, hf)
        cams[b, Cam.FX] = fx
        cams[b, Cam.FY] = fy
        cams[b, Cam.CX] = cx
        cams[b, Cam.CY] = cy
        cams[b, Cam.LIM_X_POS] = lim_x_pos
        cams[b, Cam.LIM_X_NEG] = lim_x_neg
        cams[b, Cam.LIM_Y_POS] = lim_y_pos
        cams[b, Cam.LIM_Y_NEG] = lim_y_neg
        cams[b, Cam.EARLY_A] = extent[b, 0]
        cams[b, Cam.EARLY_B] = extent[b, 1]
        cams[b, Cam.X_LO] = -cx / fx
        cams[b, Cam.X_HI] = (wf - cx) / fx
        cams[b, Cam.Y_LO] = -cy / fy
        cams[b, Cam.Y_HI] = (hf - cy) / fy


@ti.func
def view_rt(viewmats: ti.template(), b):
    """Rotation [3, 3] and translation [3] of pose ``b`` from viewmats [B, 4, 4] (rows 0-2: world-to-camera
    [R | t]; row 3: the camera centre, then 0)."""
    R = ti.Matrix([[viewmats[b, r, c] for c in ti.static(range(3))] for r in ti.static(range(3))])
    t = ti.Vector([viewmats[b, 0, 3], viewmats[b, 1, 3], viewmats[b, 2, 3]])
    return R, t


@ti.func
def camera_covariance(cov3d: ti.template(), i, R):
    """Gaussian ``i``'s covariance in the camera frame, R S R^T, from its upper triangle cov3d [N, 6]."""
    S = ti.Matrix([[cov3d[i, 0], cov3d[i, 1], cov3d[i, 2]],
                   [cov3d[i, 1], cov3d[i, 3], cov3d[i, 4]],
                   [cov3d[i, 2], cov3d[i, 4], cov3d[i, 5]]])
    return R @ S @ R.transpose()


@ti.func
def clamped_jacobian(p_c, fx, fy, lx_pos, lx_neg, ly_pos, ly_neg):
    """The projection Jacobian [2, 3] at camera-frame point p_c with x / z and y / z clamped (gsplat's rule);
    also returns the clamped x / z and y / z."""
    z = p_c[2]
    rz = 1.0 / z
    ux = ti.min(lx_pos, ti.max(-lx_neg, p_c[0] * rz))
    vy = ti.min(ly_pos, ti.max(-ly_neg, p_c[1] * rz))
    tx = z * ux
    ty = z * vy
    J = ti.Matrix([[fx * rz, 0.0, -fx * tx * rz * rz], [0.0, fy * rz, -fy * ty * rz * rz]])
    return J, ux, vy


@functools.cache
def projection_kernel(config: RasterConfig, sh_degree: int, count: bool, ellipse_tiles: bool, filtered: bool = False):
    """Compiled projection kernel for one config and SH degree; ``ellipse_tiles``: bin each Gaussian into the
    tiles its alpha ellipse reaches (else its whole box; ``footprint.uses_ellipse_tiles``); ``count``: it also
    sums each pose's tile intersections into ``totals`` [B] int64 (``tile_sort.count_tiles``, for the serial
    sort; a host array: they come back with the launch), else ``totals`` is not touched. Each pose has its own
    camera (one image size): one launch renders the poses of queries of other intrinsics as their own launches
    would, bit for bit. ``filtered``: the variant for cameras of reduced images (a record's ``Cam.FILTER`` > 0),
    which scales each opacity by ``sqrt(det(cov2 + dilation) / det(cov2 + dilation + filter))``, the footprint's
    integral kept (gsplat's "antialiased" mode, with the finer image's dilation); the plain variant adds the
    widening only, in 3DGS's arithmetic operation for operation (``Renderer`` picks the variant per call).

    Kernel arguments:
        means [N, 3], cov3d [N, 6] (xx, xy, xz, yy, yz, zz), opacities [N], sh [N, K, 3], smax [N] (largest
        scale), viewmats [B, 4, 4] (rows 0-2: world-to-camera [R | t]; row 3: the camera centre, then 0: one
        upload per call), intrin [B, 6] (each pose's fx, fy, cx, cy, dilation, filter: ``camera_records``), width,
        height (one image size for all),
        tile (tile edge in pixels: the renders' or the derivative pass's), num_poses, extent [B, 2]
        (``cull.extent_coefficient`` and ``cull.extent_pixels`` / f for each pose's camera: the bound of an
        early, conservative frustum test before the covariance);
        outputs: cams [B, Cam.SIZE] (each pose's camera record, ``layout.Cam``, also read by the derivative
        pass), depth [B, N] (camera z, the sort key), rect [B, N, footprint.RECT_SIZE] (the tile box x0, y0,
        x1, y1, exclusive ends, and with ``ellipse_tiles`` the mask of its tiles the Gaussian reaches:
        ``footprint.py``), ntiles [B, N] (tiles in the footprint; 0 = culled), packed [B, N, Rec.SIZE]: one
        record per Gaussian for the blend kernels (fields named in ``layout.Rec``).
    """
    eval_sh = make_sh_func(sh_degree)
    near, far = config.near_plane, config.far_plane
    alpha_min = config.alpha_min
    inria = config.radius_mode == "inria"
    log_inv_amin = math.log(1.0 / alpha_min)

    @ti.kernel
    def project(
        means: ti.types.ndarray(dtype=ti.f32, ndim=2),
        cov3d: ti.types.ndarray(dtype=ti.f32, ndim=2),
        opacities: ti.types.ndarray(dtype=ti.f32, ndim=1),
        sh: ti.types.ndarray(dtype=ti.f32, ndim=3),
        smax: ti.types.ndarray(dtype=ti.f32, ndim=1),
        viewmats: ti.types.ndarray(dtype=ti.f32, ndim=3),
        intrin: ti.types.ndarray(dtype=ti.f32, ndim=2),
        width: ti.i32,
        height: ti.i32,
        tile: ti.i32,
        num_poses: ti.i32,
        extent: ti.types.ndarray(dtype=ti.f32, ndim=2),
        cams: ti.types.ndarray(dtype=ti.f32, ndim=2),
        depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
        rect: ti.types.ndarray(dtype=ti.i32, ndim=3),
        ntiles: ti.types.ndarray(dtype=ti.i32, ndim=2),
        packed: ti.types.ndarray(dtype=ti.f32, ndim=3),
        totals: ti.types.ndarray(dtype=ti.i64, ndim=1),
    ):
        n = means.shape[0]
        wf = ti.cast(width, ti.f32)
        hf = ti.cast(height, ti.f32)
        tiles_x = (width + tile - 1) // tile
        tiles_y = (height + tile - 1) // tile
        tf = ti.cast(tile, ti.f32)
        # each pose's camera record, read below from memory even when all poses share one camera: the compiled
        # arithmetic then does not depend on whether they do (with loop-invariant intrinsics, fast math
        # reassociates differently), so a pose's numbers do not depend on the others of its launch
        camera_records(intrin, extent, wf, hf, num_poses, cams)
        # one task per Gaussian, its poses in an inner loop: the Gaussian's data and its pose-independent terms
        # (the opacity's logarithm) are read and computed once per batch instead of once per pose
        for i in range(n):
            p_w = ti.Vector([means[i, 0], means[i, 1], means[i, 2]])
            op = opacities[i]
            s_i = smax[i]
            lim = ti.log(ti.max(op, 1e-30)) + log_inv_amin  # alpha >= alpha_min  <=>  sigma <= lim
            extend = ti.min(3.33, ti.sqrt(ti.max(2.0 * lim, 0.0)))
            for b in range(num_poses):
                ntiles[b, i] = 0
                R, t = view_rt(viewmats, b)
                p_c = R @ p_w + t
                z = p_c[2]
                if z < near or z > far:
                    continue
                rz0 = 1.0 / z
                # box half-extent in normalised units <= early_a * smax / z + early_b (the bound of cull.py)
                ext = cams[b, Cam.EARLY_A] * s_i * rz0 + cams[b, Cam.EARLY_B]
                u0 = p_c[0] * rz0
                v0 = p_c[1] * rz0
                if (u0 - ext > cams[b, Cam.X_HI] or u0 + ext < cams[b, Cam.X_LO] or v0 - ext > cams[b, Cam.Y_HI]
                        or v0 + ext < cams[b, Cam.Y_LO]):
                    continue  # the box below would miss the image too
                Sc = camera_covariance(cov3d, i, R)
                J, _, _ = clamped_jacobian(p_c, cams[b, Cam.FX], cams[b, Cam.FY], cams[b, Cam.LIM_X_POS],
                                           cams[b, Cam.LIM_X_NEG], cams[b, Cam.LIM_Y_POS], cams[b, Cam.LIM_Y_NEG])
                rz = 1.0 / z
                cov2 = J @ Sc @ J.transpose()
                widen = cams[b, Cam.DILATION] + cams[b, Cam.FILTER]
                c00 = cov2[0, 0] + widen
                c01 = cov2[0, 1]
                c11 = cov2[1, 1] + widen
                det = c00 * c11 - c01 * c01
                if det <= 0.0:
                    continue
                op_b, lim_b, extend_b = op, lim, extend
                if ti.static(filtered):  # a reduced image's filter: the footprint widens, its integral stays
                    d00 = cov2[0, 0] + cams[b, Cam.DILATION]  # without the filter
                    d11 = cov2[1, 1] + cams[b, Cam.DILATION]
                    op_b = op * ti.sqrt(ti.max(d00 * d11 - c01 * c01, 0.0) / det)
                    lim_b = ti.log(ti.max(op_b, 1e-30)) + log_inv_amin
                    extend_b = ti.min(3.33, ti.sqrt(ti.max(2.0 * lim_b, 0.0)))
                inv_det = 1.0 / det
                mx = cams[b, Cam.FX] * p_c[0] * rz + cams[b, Cam.CX]
                my = cams[b, Cam.FY] * p_c[1] * rz + cams[b, Cam.CY]
                rx = 0.0
                ry = 0.0
                if ti.static(inria):
                    mid = 0.5 * (c00 + c11)
                    lam = mid + ti.sqrt(ti.max(0.1, mid * mid - det))
                    rx = ti.ceil(3.0 * ti.sqrt(lam))
                    ry = rx
                else:
                    if op_b < alpha_min:
                        continue
                    rx = ti.ceil(extend_b * ti.sqrt(c00))
                    ry = ti.ceil(extend_b * ti.sqrt(c11))
                if rx <= 0.0 and ry <= 0.0:
                    continue
                if mx + rx <= 0.0 or mx - rx >= wf or my + ry <= 0.0 or my - ry >= hf:
                    continue
                x0 = ti.min(ti.max(0, ti.cast(ti.floor((mx - rx) / tf), ti.i32)), tiles_x)
                x1 = ti.min(ti.max(0, ti.cast(ti.ceil((mx + rx) / tf), ti.i32)), tiles_x)
                y0 = ti.min(ti.max(0, ti.cast(ti.floor((my - ry) / tf), ti.i32)), tiles_y)
                y1 = ti.min(ti.max(0, ti.cast(ti.ceil((my + ry) / tf), ti.i32)), tiles_y)
                nt = (x1 - x0) * (y1 - y0)
                if nt <= 0:
                    continue
                ca = c11 * inv_det
                cb = -c01 * inv_det
                cc = c00 * inv_det
                mask = ~ti.u64(0)
                if ti.static(ellipse_tiles):  # only the box's tiles the alpha ellipse meets (footprint.py)
                    mask, nt = box_tile_mask(mx, my, ca, cb, cc, lim_b, x0, y0, x1, y1, tile, width, height)
                    if nt == 0:
                        continue
                depth[b, i] = z
                d = p_w - ti.Vector([viewmats[b, 3, 0], viewmats[b, 3, 1], viewmats[b, 3, 2]])
                d = d / ti.max(d.norm(), 1e-12)
                rgb = eval_sh(sh, i, d)
                # one record per Gaussian, read by both blend kernels
                packed[b, i, Rec.X] = mx
                packed[b, i, Rec.Y] = my
                packed[b, i, Rec.CA] = ca
                packed[b, i, Rec.CB] = cb
                packed[b, i, Rec.CC] = cc
                packed[b, i, Rec.OPACITY] = op_b
                packed[b, i, Rec.LIM] = lim_b
                packed[b, i, Rec.RY] = ti.sqrt(ti.max(2.0 * lim_b, 0.0) * c11) + 0.01  # y half-extent of that ellipse
                for c in ti.static(range(3)):
                    packed[b, i, Rec.RGB + c] = ti.max(rgb[c] + 0.5, 0.0)
                packed[b, i, Rec.DEPTH] = z
                rect[b, i, 0] = x0
                rect[b, i, 1] = y0
                rect[b, i, 2] = x1
                rect[b, i, 3] = y1
                if ti.static(ellipse_tiles):
                    write_mask(rect, b, i, mask)
                ntiles[b, i] = nt
        if ti.static(count):
            count_tiles(ntiles, num_poses, n, totals)

    return project
