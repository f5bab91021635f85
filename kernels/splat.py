"""The tile-parallel blends (``RasterConfig.blend`` "splat", the CPU's layout): one task per pose and tile, each
Gaussian of the tile's depth-ordered list touching only the pixels its alpha ellipse reaches (``splat_walk``), with
the image's and the fused cost's outputs of ``blend.py``'s per-pixel kernels (``splat_image_func``,
``splat_cost_kernel``); ``blend_grad.splat_grad`` runs the same walk with the pose derivatives. Along each row the
alphas come from a recurrence (``row_factors``), equal to ``blend.shade``'s exponentials to float32 rounding.
Reference twins: ``tests/test_render.py`` (against the per-pixel layout), ``tests/test_pose_grad.py``.
"""

import functools

import taichi as ti

from .blend import NSTAT, accumulate_stats, colour_of, tile_range
from .config import RasterConfig
from .grain import item, spread
from .layout import Rec

#: ``splat_walk`` takes a pixel's exponential itself where the row's recurrence lands within this fraction of
#: ``alpha_min`` or ``alpha_max`` (its rounding is a few 1e-7): the thresholds decide on ``shade``'s formula
NEAR = 1e-5


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


@ti.func
def row_factors(op, mx, ca, cb, cc, dy, lx, hx):
    """(raw, factor): ``op * exp(-sigma)`` at pixel ``lx`` of a row at offset ``dy`` from a Gaussian's centre (mean
    x ``mx``, conic ca, cb, cc), and the factor to the next pixel's. Along a row ``dx`` falls by 1 a pixel, so
    ``sigma(dx - 1) - sigma(dx) = ca (0.5 - dx) - cb dy`` rises by ``ca`` a pixel: each pixel's value is the last
    one's times ``factor``, which itself is multiplied by ``exp(-ca)`` a pixel (1 for a row of one pixel, where
    it is not needed). Equal to an exponential per pixel to float32 rounding (a few ulps over a tile's row)."""
    dx = mx - (ti.cast(lx, ti.f32) + 0.5)
    raw = op * ti.exp(-(0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy))
    factor = 1.0
    if hx - lx > 1:
        factor = ti.exp(-(ca * (0.5 - dx) - cb * dy))
    return raw, factor


@ti.func
def _same_terms(extra, dy):
    """``splat_walk``'s default row terms: the Gaussian's own."""
    return extra


def splat_walk(config: RasterConfig, tile: int, gaussian, pixel, row=None):
    """The per-tile splatting loop of the tile-parallel blends (image and pose derivatives): the Gaussians of a
    tile's list in depth order, each touching only the pixels where its alpha can reach ``alpha_min`` (the exact
    ellipse per row, clipped to its box), with the tests and transmittance of ``shade``.

    Per pixel the same Gaussians are blended in the same order and with the tests of ``shade`` (a pixel outside a
    Gaussian's ellipse has alpha < alpha_min there, so skipping it changes nothing); the alphas along a row come
    from a recurrence (:func:`row_factors`: two exponentials a row instead of one a pixel) and equal ``shade``'s to
    float32 rounding, the thresholds deciding on ``shade``'s formula (``NEAR``), so the result equals the per-pixel
    kernel's to rounding (but where a Gaussian's alpha is ``alpha_min`` to the last bit, which one kernel may blend
    and the other not); the work is proportional to the footprints instead of tile area x list length. The
    tile's accumulators are the caller's zeroed local arrays, passed as a tuple ``acc`` and filled in place (pixels
    row-major within the tile; a few arrays rather than one: Taichi compiles a 16 px tile's one [256, 28] array in
    twice the seconds, and a returned array is copied): ``acc[0]`` [tile * tile] the transmittance (set to 1 here;
    a finished pixel stores -T), the others the callbacks'. The caller's ti.funcs fill them:
    ``gaussian(packed, aux, b, g)`` -> (colour [3], extra): what a Gaussian's contributions need, loaded once per
    tile (``aux``: any template the caller passes through); ``row(extra, dy)`` -> terms: what they need along one
    row (None: ``extra`` itself); ``pixel(acc, p, colour, terms, alpha, capped, T, dx, dy, ca, cb, cc)`` adds one
    contributing Gaussian's terms to pixel ``p`` (``capped``: alpha is ``alpha_max``; T the transmittance before
    it; dx, dy its mean minus the pixel centre; ca, cb, cc its conic).
    Returns ``walk(acc, b, t, tiles_x, W, H, packed, aux, tile_start, isect, isect_base)`` -> (x0, y0): tile ``t``
    of pose ``b`` blended into ``acc``, and its first pixel.
    """
    alpha_max, alpha_min, t_eps = config.alpha_max, config.alpha_min, config.t_eps
    npx = tile * tile
    row_terms = row or _same_terms

    @ti.func
    def walk(acc: ti.template(), b, t, tiles_x, W, H, packed: ti.template(), aux: ti.template(),
             tile_start: ti.template(), isect: ti.template(), isect_base: ti.template()):
        x0, y0, x1, y1, row_left = tile_pixels(t, tiles_x, tile, W, H)
        for p in range(npx):
            acc[0][p] = 1.0
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
            decay = -1.0  # exp(-ca), made once a row of three or more pixels needs it
            col, extra = gaussian(packed, aux, b, g)
            for py in range(ly, hy):
                if row_left[py - y0] == 0:
                    continue
                dy, lx, hx = row_span(mx, my, ca, cb, cc, lim, inv_ca, py, x0, x1)
                if hx <= lx:
                    continue  # the ellipse misses this row's pixels of the tile
                base = (py - y0) * tile - x0
                terms = row_terms(extra, dy)
                # opacity * exp(-sigma) along the row by recurrence (row_factors): two exponentials a row
                raw, factor = row_factors(op, mx, ca, cb, cc, dy, lx, hx)
                if hx - lx > 2 and decay < 0.0:
                    decay = ti.exp(-ca)
                for px in range(lx, hx):
                    p = base + px
                    T = acc[0][p]
                    if T > 0.0:
                        dx = mx - (ti.cast(px, ti.f32) + 0.5)
                        sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                        val = raw
                        if ti.abs(val - alpha_min) <= NEAR * alpha_min or ti.abs(val - alpha_max) <= NEAR * alpha_max:
                            val = op * ti.exp(-sigma)  # at a threshold: decided on shade's own exponential
                        alpha = ti.min(alpha_max, val)
                        if sigma >= 0.0 and alpha >= alpha_min:
                            next_T = T * (1.0 - alpha)
                            if next_T <= t_eps:
                                acc[0][p] = -T
                                ndone += 1
                                row_left[py - y0] -= 1
                            else:
                                pixel(acc, p, col, terms, alpha, val >= alpha_max, T, dx, dy, ca, cb, cc)
                                acc[0][p] = next_T
                    raw *= factor  # the next pixel's (a row's last products, unused, may take decay's -1)
                    factor *= decay
        return x0, y0

    return walk


@ti.func
def _colour_and_depth(packed: ti.template(), aux: ti.template(), b, g):
    """The image blend's per-Gaussian terms: colour [3] and camera depth."""
    return colour_of(packed, b, g), packed[b, g, Rec.DEPTH]


@ti.func
def _colour(packed: ti.template(), aux: ti.template(), b, g):
    """The colour-only blend's per-Gaussian terms: colour [3] (no extra)."""
    return colour_of(packed, b, g), 0.0


@ti.func
def _add_colour(acc: ti.template(), p, col, extra, alpha, capped, T, dx, dy, ca, cb, cc):
    """The colour-only blend's pixel terms: accumulators (T [npx], (R, G, B) [npx, >= 3])."""
    vis = alpha * T
    for c in ti.static(range(3)):
        acc[1][p, c] += vis * col[c]


@ti.func
def _add_colour_and_depth(acc: ti.template(), p, col, depth, alpha, capped, T, dx, dy, ca, cb, cc):
    """The image blend's pixel terms: :func:`_add_colour`'s, and the depth in (R, G, B, depth) [npx, 4]."""
    _add_colour(acc, p, col, depth, alpha, capped, T, dx, dy, ca, cb, cc)
    acc[1][p, 3] += alpha * T * depth


def _make_splat_tile(config: RasterConfig, depth: bool):
    """``splat_walk`` for the image: accumulators (T [tile * tile], (R, G, B, depth) [tile * tile, 4]); without
    ``depth`` the colour alone ([tile * tile, 3])."""
    if depth:
        return splat_walk(config, config.tile_size, _colour_and_depth, _add_colour_and_depth)
    return splat_walk(config, config.tile_size, _colour, _add_colour)


@functools.cache
def splat_image_func(config: RasterConfig, depth: bool = True):
    """Tile-parallel (CPU-friendly) twin of :func:`image_func`; same arguments and outputs (without ``depth`` the
    depth image is not accumulated nor written: what a cost needs)."""
    splat_tile = _make_splat_tile(config, depth)
    tile = config.tile_size
    nacc = 4 if depth else 3

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
                trans, buf = ti.Vector.zero(ti.f32, tile * tile), ti.Matrix.zero(ti.f32, tile * tile, nacc)
                x0, y0 = splat_tile((trans, buf), b, t, tiles_x, W, H, packed, packed, tile_start, isect, isect_base)
                for py in range(y0, ti.min(y0 + tile, H)):
                    for px in range(x0, ti.min(x0 + tile, W)):
                        p = (py - y0) * tile + (px - x0)
                        T = ti.abs(trans[p])
                        for c in ti.static(range(3)):
                            out_rgb[b, py, px, c] = buf[p, c] + T * background[c]
                        out_alpha[b, py, px] = 1.0 - T
                        if ti.static(depth):
                            out_depth[b, py, px] = buf[p, 3]

    return splat_image


@functools.cache
def splat_cost_kernel(config: RasterConfig):
    """Tile-parallel twin of :func:`cost_kernel`; writes statistics per tile [B, tiles_y, tiles_x, NSTAT]."""
    splat_tile = _make_splat_tile(config, depth=False)
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
                trans, buf = ti.Vector.zero(ti.f32, tile * tile), ti.Matrix.zero(ti.f32, tile * tile, 3)
                x0, y0 = splat_tile((trans, buf), b, t, tiles_x, W, H, packed, packed, tile_start, isect, isect_base)
                st = ti.Vector([0.0] * NSTAT)
                bg = ti.Vector([background[0], background[1], background[2]])
                for py in range(y0, ti.min(y0 + tile, H)):
                    for px in range(x0, ti.min(x0 + tile, W)):
                        p = (py - y0) * tile + (px - x0)
                        T = ti.abs(trans[p])
                        if 1.0 - T >= mask_alpha:
                            rgb = ti.Vector([buf[p, 0], buf[p, 1], buf[p, 2]])
                            accumulate_stats(st, rgb + T * bg, target, py, px)
                for s in ti.static(range(NSTAT)):
                    run_stats[b, t // tiles_x, t % tiles_x, s] = st[s]

    return splat_cost
