"""Alpha-blending kernels: front-to-back compositing per pixel (CONVENTIONS §6 step 7).

Two kernels share one per-pixel loop (``shade``):
- ``image``: colour [B, H, W, 3], alpha [B, H, W] and accumulated depth [B, H, W];
- ``cost``: the fused comparison with a target image. Each task blends one 16-pixel run of a row (one tile
  wide) and accumulates photometric statistics in registers, so no image leaves the kernel; a second kernel
  reduces the runs per pose in float64, in a fixed order (deterministic, no atomics).

Statistics per pose: the ``layout.Stat`` record (n_valid, sum |r - q|, sum (r - q)^2, then per channel sum r,
sum q, sum r^2, sum q^2, sum r*q). A pixel is valid when its rendered alpha >= ``mask_alpha``.
Reference twin: ``tests/reference/render_torch.py::blend``.
"""


import functools

import taichi as ti

from .config import RasterConfig
from .grain import item, spread
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
def image_func(config: RasterConfig):
    """A ti.func (one task per pixel) writing colour [B, H, W, 3], alpha [B, H, W], accumulated depth [B, H, W];
    arguments (packed, tile_start, isect, isect_base, background, tiles_x, tiles_y, num_poses, out_rgb,
    out_alpha, out_depth), ``tiles_y`` unused (the signature of :func:`splat_image_func`)."""
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


@ti.func
def tile_pixels(t, tiles_x, tile: ti.template(), W, H):
    """(x0, y0, x1, y1, row_left): tile ``t``'s pixels [x0, x1) x [y0, y1) of an image W x H in tiles of ``tile``
    pixels, ``tiles_x`` per row; row_left [tile]: the pixels of each of its rows (0 below the image)."""
    x0 = (t % tiles_x) * tile
    y0 = (t // tiles_x) * tile
    x1 = ti.min(x0 + tile, W)
    y1 = ti.min(y0 + tile, H)
    row_left = ti.Vector([0] * tile)
    for r in ti.static(range(tile)):
        row_left[r] = x1 - x0 if y0 + r < y1 else 0
    return x0, y0, x1, y1, row_left


@ti.func
def ellipse_of(packed: ti.template(), b, g):
    """(mx, my, ca, cb, cc, lim): Gaussian ``g``'s 2D mean, conic and alpha limit (``Rec.LIM``: alpha >=
    alpha_min <=> sigma <= lim) in pose ``b``'s records ``packed`` [B, N, Rec.SIZE]."""
    return (packed[b, g, Rec.X], packed[b, g, Rec.Y], packed[b, g, Rec.CA], packed[b, g, Rec.CB],
            packed[b, g, Rec.CC], packed[b, g, Rec.LIM])


@ti.func
def rows_reached(my, ry, y0, y1):
    """[ly, hy): the rows of a tile's rows [y0, y1) a Gaussian's alpha ellipse (centre row ``my``, half-extent
    ``ry``, ``Rec.RY``) may reach. Integer bounds by truncation: never tighter than ceil / floor would give (a
    superset of rows, each pixel still tested exactly), and cheaper than calls to ceil / floor."""
    return ti.max(y0, ti.cast(my - ry - 0.5, ti.i32)), ti.min(y1, ti.cast(my + ry - 0.5, ti.i32) + 1)


@ti.func
def row_span(mx, my, ca, cb, cc, lim, inv_ca, py, x0, x1):
    """(dy, lx, hx): row ``py``'s offset ``dy = my - (py + 0.5)`` from a Gaussian's centre and the pixels
    [lx, hx) of the tile's columns [x0, x1) inside its ellipse ``sigma <= lim`` (conic ca, cb, cc; ``inv_ca`` =
    1 / ca), widened by 0.01 px per side: every pixel whose alpha reaches ``alpha_min`` (an empty span if none)."""
    dy = my - (ti.cast(py, ti.f32) + 0.5)
    # 0.5 ca dx^2 + (cb dy) dx + 0.5 cc dy^2 - lim <= 0
    bq = cb * dy
    disc = bq * bq - ca * (cc * dy * dy - 2.0 * lim)
    lx = x1
    hx = x0
    if disc >= 0.0 and lim > 0.0:
        sq = ti.sqrt(disc)
        # dx = mx - (px + 0.5) in [(-bq - sq) / ca, (-bq + sq) / ca] (+- 0.01 margin)
        lx = ti.max(x0, ti.cast(mx - 0.51 - (sq - bq) * inv_ca, ti.i32))
        hx = ti.min(x1, ti.cast(mx - 0.49 + (sq + bq) * inv_ca, ti.i32) + 1)
    return dy, lx, hx


def splat_walk(config: RasterConfig, tile: int, nacc: int, gaussian, pixel):
    """The per-tile splatting loop of the tile-parallel blends (image and pose derivatives): the Gaussians of a
    tile's list in depth order, each touching only the pixels where its alpha can reach ``alpha_min`` (the exact
    ellipse per row, clipped to its box), with the tests and transmittance of ``shade``.

    Per pixel the same Gaussians are blended in the same order and with the same arithmetic as ``shade`` (a pixel
    outside a Gaussian's ellipse has alpha < alpha_min there, so skipping it changes nothing), so the result equals
    the per-pixel kernel's; the work is proportional to the footprints instead of tile area x list length. The
    tile's accumulators live in a local array [tile * tile, nacc] (row-major within the tile): field 0 the
    transmittance (a finished pixel stores -T), the others the caller's. Two ti.funcs fill them:
    ``gaussian(packed, aux, b, g)`` -> (colour [3], extra): what a Gaussian's contributions need, loaded once per
    tile (``aux``: any template the caller passes through); ``pixel(acc, p, colour, extra, alpha, capped, T, dx, dy,
    ca, cb, cc)`` adds one contributing Gaussian's terms to pixel ``p`` (``capped``: alpha is ``alpha_max``; T the
    transmittance before it; dx, dy its mean minus the pixel centre; ca, cb, cc its conic).
    Returns ``walk(b, t, tiles_x, W, H, packed, aux, tile_start, isect, isect_base)`` -> (acc, x0, y0): tile ``t``
    of pose ``b`` and its first pixel.
    """
    alpha_max, alpha_min, t_eps = config.alpha_max, config.alpha_min, config.t_eps
    npx = tile * tile

    @ti.func
    def walk(b, t, tiles_x, W, H, packed: ti.template(), aux: ti.template(), tile_start: ti.template(),
             isect: ti.template(), isect_base: ti.template()):
        x0, y0, x1, y1, row_left = tile_pixels(t, tiles_x, tile, W, H)
        acc = ti.Matrix.zero(ti.f32, npx, nacc)
        for p in range(npx):
            acc[p, 0] = 1.0
        npix = (x1 - x0) * (y1 - y0)
        ndone = 0
        start, end = tile_range(b, t, tile_start, isect_base)
        for k in range(start, end):
            if ndone >= npix:
                break
            g = isect[k]
            mx, my, ca, cb, cc, lim = ellipse_of(packed, b, g)
            op = packed[b, g, Rec.OPACITY]
            ly, hy = rows_reached(my, packed[b, g, Rec.RY], y0, y1)
            inv_ca = 1.0 / ca
            col, extra = gaussian(packed, aux, b, g)
            for py in range(ly, hy):
                if row_left[py - y0] == 0:
                    continue
                dy, lx, hx = row_span(mx, my, ca, cb, cc, lim, inv_ca, py, x0, x1)
                row = (py - y0) * tile - x0
                for px in range(lx, hx):
                    p = row + px
                    T = acc[p, 0]
                    if T > 0.0:
                        dx = mx - (ti.cast(px, ti.f32) + 0.5)
                        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        raw = op * ti.exp(-sigma)
                        alpha = ti.min(alpha_max, raw)
                        if sigma >= 0.0 and alpha >= alpha_min:
                            next_T = T * (1.0 - alpha)
                            if next_T <= t_eps:
                                acc[p, 0] = -T
                                ndone += 1
                                row_left[py - y0] -= 1
                            else:
                                pixel(acc, p, col, extra, alpha, raw >= alpha_max, T, dx, dy, ca, cb, cc)
                                acc[p, 0] = next_T
        return acc, x0, y0

    return walk


@ti.func
def _colour_and_depth(packed: ti.template(), aux: ti.template(), b, g):
    """The image blend's per-Gaussian terms: colour [3] and camera depth."""
    return colour_of(packed, b, g), packed[b, g, Rec.DEPTH]


@ti.func
def _add_colour_and_depth(acc: ti.template(), p, col, depth, alpha, capped, T, dx, dy, ca, cb, cc):
    """The image blend's pixel terms: accumulators (T, R, G, B, depth)."""
    vis = alpha * T
    for c in ti.static(range(3)):
        acc[p, 1 + c] += vis * col[c]
    acc[p, 4] += vis * depth


def _make_splat_tile(config: RasterConfig):
    """``splat_walk`` for the image: accumulators [tile * tile, 5] (T, R, G, B, depth)."""
    return splat_walk(config, config.tile_size, 5, _colour_and_depth, _add_colour_and_depth)


@functools.cache
def splat_image_func(config: RasterConfig):
    """Tile-parallel (CPU-friendly) twin of :func:`image_func`; same arguments and outputs."""
    splat_tile = _make_splat_tile(config)
    tile = config.tile_size

    @ti.func
    def splat_image(packed: ti.template(), tile_start: ti.template(), isect: ti.template(), isect_base: ti.template(),
                    background: ti.template(), tiles_x, tiles_y, num_poses, out_rgb: ti.template(),
                    out_alpha: ti.template(), out_depth: ti.template()):
        H = out_rgb.shape[1]
        W = out_rgb.shape[2]
        stride = ti.static(spread())  # one task per tile on the CPU (grain.py)
        nt = tiles_x * tiles_y
        for task in range(num_poses * nt * stride):
            is_item, b, t = item(task, stride, nt)
            if is_item:
                buf, x0, y0 = splat_tile(b, t, tiles_x, W, H, packed, packed, tile_start, isect, isect_base)
                for py in range(y0, ti.min(y0 + tile, H)):
                    for px in range(x0, ti.min(x0 + tile, W)):
                        p = (py - y0) * tile + (px - x0)
                        T = ti.abs(buf[p, 0])
                        for c in ti.static(range(3)):
                            out_rgb[b, py, px, c] = buf[p, 1 + c] + T * background[c]
                        out_alpha[b, py, px] = 1.0 - T
                        out_depth[b, py, px] = buf[p, 4]

    return splat_image


@functools.cache
def splat_cost_kernel(config: RasterConfig):
    """Tile-parallel twin of :func:`cost_kernel`; writes statistics per tile [B, tiles_y, tiles_x, NSTAT]."""
    splat_tile = _make_splat_tile(config)
    tile = config.tile_size

    @ti.kernel
    def splat_cost(
        packed: ti.types.ndarray(dtype=ti.f32, ndim=3),
        tile_start: ti.types.ndarray(dtype=ti.i32, ndim=2),
        isect: ti.types.ndarray(dtype=ti.i32, ndim=1),
        isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
        background: ti.types.ndarray(dtype=ti.f32, ndim=1),
        tiles_x: ti.i32,
        tiles_y: ti.i32,
        num_poses: ti.i32,
        target: ti.types.ndarray(dtype=ti.f32, ndim=3),
        mask_alpha: ti.f32,
        run_stats: ti.types.ndarray(dtype=ti.f32, ndim=4),
    ):
        H = target.shape[0]
        W = target.shape[1]
        stride = ti.static(spread())  # one task per tile on the CPU (grain.py)
        nt = tiles_x * tiles_y
        for task in range(num_poses * nt * stride):
            is_item, b, t = item(task, stride, nt)
            if is_item:
                buf, x0, y0 = splat_tile(b, t, tiles_x, W, H, packed, packed, tile_start, isect, isect_base)
                st = ti.Vector([0.0] * NSTAT)
                bg = ti.Vector([background[0], background[1], background[2]])
                for py in range(y0, ti.min(y0 + tile, H)):
                    for px in range(x0, ti.min(x0 + tile, W)):
                        p = (py - y0) * tile + (px - x0)
                        T = ti.abs(buf[p, 0])
                        if 1.0 - T >= mask_alpha:
                            rgb = ti.Vector([buf[p, 1], buf[p, 2], buf[p, 3]])
                            accumulate_stats(st, rgb + T * bg, target, py, px)
                for s in ti.static(range(NSTAT)):
                    run_stats[b, t // tiles_x, t % tiles_x, s] = st[s]

    return splat_cost


@functools.cache
def image_kernel(config: RasterConfig, splat: bool):
    """The image blend (:func:`splat_image_func` or :func:`image_func`) in a launch of its own."""
    blend = splat_image_func(config) if splat else image_func(config)
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
