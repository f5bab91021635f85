"""Alpha-blending kernels: front-to-back compositing per pixel (CONVENTIONS §6 step 7).

Two kernels share one per-pixel loop (``shade``):
- ``image``: colour [B, H, W, 3], alpha [B, H, W] and accumulated depth [B, H, W];
- ``cost``: the fused comparison with a target image. Each task blends one 16-pixel run of a row (one tile
  wide) and accumulates photometric statistics in registers, so no image leaves the kernel; a second kernel
  reduces the runs per pose in float64, in a fixed order (deterministic, no atomics).

Statistics per pose: the ``layout.Stat`` record (n_valid, sum |r - q|, sum (r - q)^2, then per channel sum r,
sum q, sum r^2, sum q^2, sum r*q). A pixel is valid when its rendered alpha >= ``mask_alpha``.
The tile-parallel twins of both (the CPU's layout) are in ``splat.py``.
Reference twin: ``tests/reference/render_torch.py::blend``.
"""


import functools

import taichi as ti

from .config import RasterConfig
from .layout import Rec, Stat

NSTAT = Stat.SIZE


@ti.func
def accumulate_stats(acc: ti.template(), rgb, target: ti.template(), py, px):
    """Add one valid pixel's terms to the ``Stat`` record ``acc`` (in place, fixed order)."""
    acc[Stat.N] += 1.0
    for c in ti.static(range(3)):
        r = rgb[c]
        q = target[py, px, c]
        e = r - q
        acc[Stat.SAD] += ti.abs(e)
        acc[Stat.SSD] += e * e
        acc[ti.static(Stat.at(c, Stat.SR))] += r
        acc[ti.static(Stat.at(c, Stat.SQ))] += q
        acc[ti.static(Stat.at(c, Stat.SRR))] += r * r
        acc[ti.static(Stat.at(c, Stat.SQQ))] += q * q
        acc[ti.static(Stat.at(c, Stat.SRQ))] += r * q


@ti.func
def tile_range(b, t_id, tile_start: ti.template(), isect_base: ti.template()):
    """[start, end) of tile ``t_id``'s depth-ordered Gaussian list of pose ``b`` in ``isect``."""
    base = ti.cast(isect_base[b], ti.i32)
    return base + tile_start[b, t_id], base + tile_start[b, t_id + 1]


@ti.func
def colour_of(packed: ti.template(), b, g):
    """Gaussian ``g``'s colour [3] in pose ``b``'s records ``packed`` [B, N, Rec.SIZE]."""
    return ti.Vector([packed[b, g, Rec.RGB], packed[b, g, Rec.RGB + 1], packed[b, g, Rec.RGB + 2]])


def _make_shade(config: RasterConfig):
    alpha_max, alpha_min, t_eps, tile = config.alpha_max, config.alpha_min, config.t_eps, config.tile_size

    @ti.func
    def shade(b, px, py, tiles_x, packed: ti.template(), tile_start: ti.template(), isect: ti.template(),
              isect_base: ti.template()):
        start, end = tile_range(b, (py // tile) * tiles_x + px // tile, tile_start, isect_base)
        fx = ti.cast(px, ti.f32) + 0.5
        fy = ti.cast(py, ti.f32) + 0.5
        T = 1.0
        C = ti.Vector([0.0, 0.0, 0.0])
        D = 0.0
        for k in range(start, end):
            g = isect[k]
            dx = packed[b, g, Rec.X] - fx
            dy = packed[b, g, Rec.Y] - fy
            sigma = (0.5 * (packed[b, g, Rec.CA] * dx * dx + packed[b, g, Rec.CC] * dy * dy)
                     + packed[b, g, Rec.CB] * dx * dy)
            alpha = ti.min(alpha_max, packed[b, g, Rec.OPACITY] * ti.exp(-sigma))
            if sigma < 0.0 or alpha < alpha_min:
                continue
            next_T = T * (1.0 - alpha)
            if next_T <= t_eps:
                break
            vis = alpha * T
            C += vis * colour_of(packed, b, g)
            D += vis * packed[b, g, Rec.DEPTH]
            T = next_T
        return C, T, D

    return shade


@functools.cache
def image_func(config: RasterConfig, depth: bool = True):
    """A ti.func (one task per pixel) writing colour [B, H, W, 3], alpha [B, H, W], accumulated depth [B, H, W]
    (not written without ``depth``); arguments (packed, tile_start, isect, isect_base, background, tiles_x,
    tiles_y, num_poses, out_rgb, out_alpha, out_depth), ``tiles_y`` unused (the signature of
    :func:`splat_image_func`)."""
    shade = _make_shade(config)

    @ti.func
    def blend_image(packed: ti.template(), tile_start: ti.template(), isect: ti.template(), isect_base: ti.template(),
                    background: ti.template(), tiles_x, tiles_y, num_poses, out_rgb: ti.template(),
                    out_alpha: ti.template(), out_depth: ti.template()):
        H = out_rgb.shape[1]
        W = out_rgb.shape[2]
        for b, py, px in ti.ndrange(num_poses, H, W):
            C, T, D = shade(b, px, py, tiles_x, packed, tile_start, isect, isect_base)
            for c in ti.static(range(3)):
                out_rgb[b, py, px, c] = C[c] + T * background[c]
            out_alpha[b, py, px] = 1.0 - T
            if ti.static(depth):
                out_depth[b, py, px] = D

    return blend_image


@functools.cache
def cost_kernel(config: RasterConfig):
    """Kernel blending and comparing with ``target`` [H, W, 3]; writes run statistics [B, H, tiles_x, NSTAT]."""
    shade = _make_shade(config)
    tile = config.tile_size

    @ti.kernel
    def blend_cost(
        packed: ti.types.ndarray(dtype=ti.f32, ndim=3),
        tile_start: ti.types.ndarray(dtype=ti.i32, ndim=2),
        isect: ti.types.ndarray(dtype=ti.i32, ndim=1),
        isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
        background: ti.types.ndarray(dtype=ti.f32, ndim=1),
        tiles_x: ti.i32,
        num_poses: ti.i32,
        target: ti.types.ndarray(dtype=ti.f32, ndim=3),
        mask_alpha: ti.f32,
        run_stats: ti.types.ndarray(dtype=ti.f32, ndim=4),
    ):
        H = target.shape[0]
        W = target.shape[1]
        for b, py, run in ti.ndrange(num_poses, H, tiles_x):
            acc = ti.Vector([0.0] * NSTAT)
            bg = ti.Vector([background[0], background[1], background[2]])
            for dx in range(tile):
                px = run * tile + dx
                if px < W:
                    C, T, D = shade(b, px, py, tiles_x, packed, tile_start, isect, isect_base)
                    if 1.0 - T >= mask_alpha:
                        accumulate_stats(acc, C + T * bg, target, py, px)
            for s in ti.static(range(NSTAT)):
                run_stats[b, py, run, s] = acc[s]

    return blend_cost


@ti.func
def reduce_rows(run_stats: ti.template(), num_poses, out: ti.template()):
    """Sum run statistics [B, H, TX, S] into per-pose totals ``out`` [>= num_poses, S] in float64, in a fixed order
    (row, then run). S is read from ``out``, so the blend's ``Stat`` record and the window kernels' rows share it;
    ``out`` may be a host (numpy) array: the totals then arrive without a read-back launch."""
    H = run_stats.shape[1]
    TX = run_stats.shape[2]
    for b, s in ti.ndrange(num_poses, out.shape[1]):
        tot = ti.f64(0.0)
        for y in range(H):
            for r in range(TX):
                tot += ti.cast(run_stats[b, y, r, s], ti.f64)
        out[b, s] = tot


@functools.cache
def reduce_kernel():
    """:func:`reduce_rows` in a launch of its own."""

    @ti.kernel
    def reduce_stats(run_stats: ti.types.ndarray(dtype=ti.f32, ndim=4), num_poses: ti.i32,
                     out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        reduce_rows(run_stats, num_poses, out)

    return reduce_stats


@functools.cache
def image_kernel(blend):
    """The image blend ``blend`` (what :func:`image_func` or ``splat.splat_image_func`` returns for a
    ``RasterConfig``) in a launch of its own, taking the blend's arguments."""
    f32, i32 = ti.f32, ti.i32

    @ti.kernel
    def blend_images(packed: ti.types.ndarray(dtype=f32, ndim=3), tile_start: ti.types.ndarray(dtype=i32, ndim=2),
                     isect: ti.types.ndarray(dtype=i32, ndim=1), isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
                     background: ti.types.ndarray(dtype=f32, ndim=1), tiles_x: i32, tiles_y: i32, num_poses: i32,
                     out_rgb: ti.types.ndarray(dtype=f32, ndim=4), out_alpha: ti.types.ndarray(dtype=f32, ndim=3),
                     out_depth: ti.types.ndarray(dtype=f32, ndim=3)):
        blend(packed, tile_start, isect, isect_base, background, tiles_x, tiles_y, num_poses, out_rgb, out_alpha,
              out_depth)

    return blend_images
