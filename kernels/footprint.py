"""A Gaussian's tile footprint: the tiles of its box that its alpha ellipse can reach.

A Gaussian changes a pixel only where ``alpha >= alpha_min``, i.e. inside the ellipse ``sigma <= LIM`` of its
record (``layout.Rec``). The projection bins it into every tile of the ellipse's bounding box; a long, tilted
ellipse misses the box's corner tiles, and a sub-pixel one often misses all but one of the tiles its box
straddles. :func:`box_tile_mask` marks the box's tiles the ellipse meets, so the tile sort leaves the others out:
shorter lists for the blend and the sort, the same images bit for bit (a dropped tile has no pixel where the
Gaussian's alpha reaches ``alpha_min``: the test is conservative by ``SIGMA_MARGIN`` and ``PIXEL_MARGIN``).

The footprint travels in the projection's ``rect`` [B, N, RECT_SIZE]: the box's tile x0, y0, x1, y1 (exclusive
ends), then the 64-bit mask of the box's tiles (row-major in the box) as two int32 words, low then high. A box of
more than ``MASK_TILES`` tiles keeps all of them (mask all ones). Binning by box, the projection writes no
mask and the sorts read none (``read_mask`` and ``in_footprint`` fold to constants).
"""

import taichi as ti

from .config import RasterConfig

RECT_SIZE = 6  # x0, y0, x1, y1, mask low word, mask high word
MASK_TILES = 64  # boxes of at most this many tiles carry a mask; larger ones keep every tile
SIGMA_MARGIN = 1e-3  # the ellipse tested is sigma <= LIM + SIGMA_MARGIN (f32 rounding of sigma)
PIXEL_MARGIN = 0.1  # pixels added on each side of the region tested (f32 rounding of the mean)


def uses_ellipse_tiles(config: RasterConfig, arch: str) -> bool:
    """Whether the projection bins by the ellipse on backend ``arch`` (``RasterConfig.tile_test``; "auto": on
    CUDA, whose per-pixel blend walks every entry of a tile's list; not on the CPU, whose splat blend already
    skips a Gaussian's rows outside its ellipse and where the test cost more than it saved:
    ``benchmarks/tile_lists.md``)."""
    if config.tile_test == "auto":
        return arch == "cuda"
    return config.tile_test == "ellipse"


@ti.func
def ellipse_meets_rect(mx, my, ca, cb, cc, lim, x_lo, x_hi, y_lo, y_hi) -> bool:
    """Whether ``sigma(p) = 0.5 (ca dx^2 + cc dy^2) + cb dx dy`` (d = p - (mx, my)) is at most ``lim`` somewhere
    in the rectangle [x_lo, x_hi] x [y_lo, y_hi] (pixel units). Exact for a positive-definite conic: the minimum
    is at the mean when it is inside, else on an edge, where it is a clamped one-dimensional minimum."""
    u0 = x_lo - mx
    u1 = x_hi - mx
    v0 = y_lo - my
    v1 = y_hi - my
    best = 0.0
    if not (u0 <= 0.0 <= u1 and v0 <= 0.0 <= v1):
        best = ti.math.inf
        for e in ti.static(range(2)):
            u = u0 if e == 0 else u1  # a vertical edge: minimise over v
            v = ti.min(ti.max(-cb * u / cc, v0), v1)
            best = ti.min(best, 0.5 * (ca * u * u + cc * v * v) + cb * u * v)
            v2 = v0 if e == 0 else v1  # a horizontal edge: minimise over u
            u2 = ti.min(ti.max(-cb * v2 / ca, u0), u1)
            best = ti.min(best, 0.5 * (ca * u2 * u2 + cc * v2 * v2) + cb * u2 * v2)
    return best <= lim


@ti.func
def box_tile_mask(mx, my, ca, cb, cc, lim, x0, y0, x1, y1, tile, width, height):
    """(mask, count): the tiles of the box [x0, x1) x [y0, y1) (tile units, non-empty) whose pixel centres the
    ellipse ``sigma <= lim`` (conic ca, cb, cc about (mx, my)) may reach, and their number. Boxes of more than
    ``MASK_TILES`` tiles: all ones and the box's tile count."""
    nbox = (x1 - x0) * (y1 - y0)
    mask = ~ti.u64(0)
    count = nbox
    if nbox <= MASK_TILES:
        mask = ti.u64(0)
        count = 0
        k = 0
        limit = lim + SIGMA_MARGIN
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                # the tile's first and last pixel centres, widened by the margin
                xa = ti.cast(tx * tile, ti.f32) + 0.5 - PIXEL_MARGIN
                xb = ti.cast(ti.min((tx + 1) * tile, width), ti.f32) - 0.5 + PIXEL_MARGIN
                ya = ti.cast(ty * tile, ti.f32) + 0.5 - PIXEL_MARGIN
                yb = ti.cast(ti.min((ty + 1) * tile, height), ti.f32) - 0.5 + PIXEL_MARGIN
                if ellipse_meets_rect(mx, my, ca, cb, cc, limit, xa, xb, ya, yb):
                    mask |= ti.u64(1) << ti.cast(k, ti.u64)
                    count += 1
                k += 1
    return mask, count


@ti.func
def write_mask(rect: ti.template(), b, i, mask):
    """Store a footprint mask in ``rect[b, i, 4:6]`` (low word, high word)."""
    rect[b, i, 4] = ti.cast(mask & ti.u64(0xFFFFFFFF), ti.i32)
    rect[b, i, 5] = ti.cast(mask >> ti.u64(32), ti.i32)


@ti.func
def read_mask(rect: ti.template(), b, i, ellipse: ti.template()) -> ti.u64:
    """The footprint mask of ``rect[b, i]``; without ``ellipse`` (binning by box) all ones, nothing read."""
    mask = ~ti.u64(0)
    if ti.static(ellipse):
        lo = ti.cast(ti.cast(rect[b, i, 4], ti.u32), ti.u64)
        hi = ti.cast(ti.cast(rect[b, i, 5], ti.u32), ti.u64)
        mask = lo | (hi << ti.u64(32))
    return mask


@ti.func
def in_footprint(mask, k, ellipse: ti.template()) -> bool:
    """Whether the box's ``k``-th tile (row-major) is in the footprint ``mask`` (every tile past the 64th is:
    such boxes carry all ones); without ``ellipse``, every tile, a constant the compiler folds."""
    inside = True
    if ti.static(ellipse):
        if k < MASK_TILES:  # no shift by 64 or more
            inside = (mask >> ti.cast(k, ti.u64)) & ti.u64(1) != ti.u64(0)
    return inside
