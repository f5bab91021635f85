"""Windowed structural comparison (SSIM and its contrast-structure term), a fused follow-up to blending.

The blend kernel leaves the rendered colour [B, H, W, 3] and alpha [B, H, W] on the device; these kernels read
them there and return one (sum, count) pair per pose, so no image leaves the device.

Per pixel p and channel c, with Gaussian window weights w (sigma ``SIGMA``, radius ``RADIUS``, normalised,
separable; coordinates outside the image are clamped to the border, i.e. replicate padding):

    mu_r = sum w r,  mu_q = sum w q
    s_rr = sum w r^2 - mu_r^2,  s_qq = sum w q^2 - mu_q^2,  s_rq = sum w r q - mu_r mu_q
    cs   = (2 s_rq + C2) / (s_rr + s_qq + C2)
    ssim = cs * (2 mu_r mu_q + C1) / (mu_r^2 + mu_q^2 + C1)

The pixel's value is the mean over the three channels; a pixel counts when its rendered alpha >= ``mask_alpha``.
``cs`` compares local structure only (invariant to a brightness offset and robust to gain), which is what
survives between a real photograph and an imperfect map. Sums run in a fixed order (one task per row, then one
per pose in float64 by ``blend.reduce_rows``): deterministic.

Query statistics hold Q queries ``[Q, H, W, 3, NQ]``; pose ``b`` of a launch is compared with query
``query_index[b]`` ([B] int32), so one launch scores the poses of many queries of one size, each pose's numbers
those of a launch of its own.
Reference twin: ``tests/reference/render_torch.py::window_cost``.
"""

import functools
import math

import taichi as ti

from .blend import image_func, reduce_rows
from .grain import item, spread
from .splat import splat_image_func

SIGMA = 1.5
RADIUS = 5
C1 = 0.01 ** 2
C2 = 0.03 ** 2
NQ = 3  # per channel query statistics: mu_q, s_qq, q
BLOCK = 8  # rows per task of the CPU's column passes (block_moments, window_grad.window_filter; 4, 16 slower)


def window_weights() -> list[float]:
    """Normalised 1D Gaussian weights, length 2 * RADIUS + 1."""
    w = [math.exp(-0.5 * (k / SIGMA) ** 2) for k in range(-RADIUS, RADIUS + 1)]
    s = sum(w)
    return [x / s for x in w]


_W = window_weights()


@ti.func
def _query_row(q: ti.template(), y, W, tmp: ti.template()):
    """The query statistics' horizontal pass along row ``y`` (the CPU's), channel by channel, its taps sliding
    along the row in registers as :func:`_horizontal_row`'s."""
    for c in range(3):
        v = ti.Vector([0.0] * (2 * RADIUS + 1))
        for j in ti.static(range(2 * RADIUS + 1)):
            v[j] = q[y, ti.min(ti.max(j - RADIUS, 0), W - 1), c]
        for x in range(W):
            m = 0.0
            m2 = 0.0
            for j in ti.static(range(2 * RADIUS + 1)):
                m += ti.static(_W[j]) * v[j]
                m2 += ti.static(_W[j]) * v[j] * v[j]
            tmp[y, x, c, 0] = m
            tmp[y, x, c, 1] = m2
            for j in ti.static(range(2 * RADIUS)):
                v[j] = v[j + 1]
            v[2 * RADIUS] = q[y, ti.min(x + RADIUS + 1, W - 1), c]


@ti.func
def _query_horizontal_at(q: ti.template(), y, x, W, tmp: ti.template()):
    """The query statistics' horizontal pass at one pixel (one task per pixel)."""
    for c in ti.static(range(3)):
        m = 0.0
        m2 = 0.0
        for j in ti.static(range(2 * RADIUS + 1)):
            v = q[y, ti.min(ti.max(x + j - RADIUS, 0), W - 1), c]
            m += ti.static(_W[j]) * v
            m2 += ti.static(_W[j]) * v * v
        tmp[y, x, c, 0] = m
        tmp[y, x, c, 1] = m2


@ti.func
def _query_vertical_at(q: ti.template(), tmp: ti.template(), slot, y, x, H, out: ti.template()):
    """The query statistics' vertical pass at one pixel, into slot ``slot`` of ``out``."""
    for c in ti.static(range(3)):
        m = 0.0
        m2 = 0.0
        for i in ti.static(range(2 * RADIUS + 1)):
            yy = ti.min(ti.max(y + i - RADIUS, 0), H - 1)
            m += ti.static(_W[i]) * tmp[yy, x, c, 0]
            m2 += ti.static(_W[i]) * tmp[yy, x, c, 1]
        out[slot, y, x, c, 0] = m
        out[slot, y, x, c, 1] = ti.max(m2 - m * m, 0.0)
        out[slot, y, x, c, 2] = q[y, x, c]


@functools.cache
def query_stats_kernel():
    """Statistics of the query ``q`` [H, W, 3] into slot ``slot`` of ``out`` [Q, H, W, 3, NQ]: windowed mean,
    windowed variance and the pixel itself, per channel; the window is separable, so a horizontal pass into
    ``tmp`` [H, W, 3, 2] (q and q^2 filtered along rows) and a vertical one (as the rendering's, :func:`horizontal`
    and :func:`vertical_moments`). On the CPU the horizontal pass runs one task per row (``grain.py``), its taps
    sliding along the row (:func:`_query_row`); elsewhere, and for the vertical pass, one task per pixel."""

    @ti.kernel
    def query_stats(q: ti.types.ndarray(dtype=ti.f32, ndim=3), slot: ti.i32,
                    tmp: ti.types.ndarray(dtype=ti.f32, ndim=4), out: ti.types.ndarray(dtype=ti.f32, ndim=5)):
        H = q.shape[0]
        W = q.shape[1]
        stride = ti.static(spread())
        if ti.static(stride > 1):
            for task in range(H * stride):
                is_item, _, y = item(task, stride, H)
                if is_item:
                    _query_row(q, y, W, tmp)
        else:
            for y, x in ti.ndrange(H, W):
                _query_horizontal_at(q, y, x, W, tmp)
        for y, x in ti.ndrange(H, W):
            _query_vertical_at(q, tmp, slot, y, x, H, out)

    return query_stats


@functools.cache
def copy_query_kernel():
    """Copy slot ``src_slot`` of query statistics ``src`` [Q1, H, W, 3, NQ] into slot ``dst_slot`` of ``dst``."""

    @ti.kernel
    def copy_query(src: ti.types.ndarray(dtype=ti.f32, ndim=5), src_slot: ti.i32,
                   dst: ti.types.ndarray(dtype=ti.f32, ndim=5), dst_slot: ti.i32):
        for y, x, c, k in ti.ndrange(src.shape[1], src.shape[2], 3, NQ):
            dst[dst_slot, y, x, c, k] = src[src_slot, y, x, c, k]

    return copy_query


@ti.func
def _horizontal_at(rgb: ti.template(), qstats: ti.template(), qi, b, y, x, W, out: ti.template()):
    """:func:`horizontal` at one pixel."""
    for c in ti.static(range(3)):
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        for j in ti.static(range(2 * RADIUS + 1)):
            xx = ti.min(ti.max(x + j - RADIUS, 0), W - 1)
            r = rgb[b, y, xx, c]
            w = ti.static(_W[j])
            s1 += w * r
            s2 += w * r * r
            s3 += w * r * qstats[qi, y, xx, c, 2]
        out[b, y, x, c, 0] = s1
        out[b, y, x, c, 1] = s2
        out[b, y, x, c, 2] = s3


@ti.func
def _horizontal_row(rgb: ti.template(), qstats: ti.template(), qi, b, y, W, out: ti.template()):
    """:func:`horizontal` along one row, channel by channel: the window's taps slide along the row in registers
    (one load of the rendering and of the query a pixel instead of one a tap); the terms and their order are
    :func:`_horizontal_at`'s (the compiler may fuse the multiply-adds its own way: float32 rounding)."""
    for c in range(3):
        r = ti.Vector([0.0] * (2 * RADIUS + 1))
        q = ti.Vector([0.0] * (2 * RADIUS + 1))
        for j in ti.static(range(2 * RADIUS + 1)):
            xx = ti.min(ti.max(j - RADIUS, 0), W - 1)
            r[j] = rgb[b, y, xx, c]
            q[j] = qstats[qi, y, xx, c, 2]
        for x in range(W):
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            for j in ti.static(range(2 * RADIUS + 1)):
                w = ti.static(_W[j])
                s1 += w * r[j]
                s2 += w * r[j] * r[j]
                s3 += w * r[j] * q[j]
            out[b, y, x, c, 0] = s1
            out[b, y, x, c, 1] = s2
            out[b, y, x, c, 2] = s3
            for j in ti.static(range(2 * RADIUS)):
                r[j] = r[j + 1]
                q[j] = q[j + 1]
            xx = ti.min(x + RADIUS + 1, W - 1)
            r[2 * RADIUS] = rgb[b, y, xx, c]
            q[2 * RADIUS] = qstats[qi, y, xx, c, 2]


@ti.func
def horizontal(rgb: ti.template(), qstats: ti.template(), query_index: ti.template(), num_poses, out: ti.template()):
    """First (horizontal) window pass over the rendering: out [B, H, W, 3, 3] = filtered r, r^2, r q per channel.
    On the CPU one task per image row (``grain.py``: no index division per pixel), its taps sliding along the row
    (:func:`_horizontal_row`); elsewhere one task per pixel."""
    H = rgb.shape[1]
    W = rgb.shape[2]
    stride = ti.static(spread())
    if ti.static(stride > 1):
        for task in range(num_poses * H * stride):
            is_item, b, y = item(task, stride, H)
            if is_item:
                _horizontal_row(rgb, qstats, query_index[b], b, y, W, out)
    else:
        for b, y, x in ti.ndrange(num_poses, H, W):
            _horizontal_at(rgb, qstats, query_index[b], b, y, x, W, out)


@ti.func
def vertical_moments(hbuf: ti.template(), b, y, x, c, H):
    """The vertical window pass at one pixel and channel: windowed r, r^2 and r q (from ``horizontal``)."""
    m = 0.0
    m2 = 0.0
    mrq = 0.0
    for i in ti.static(range(2 * RADIUS + 1)):
        yy = ti.min(ti.max(y + i - RADIUS, 0), H - 1)
        w = ti.static(_W[i])
        m += w * hbuf[b, yy, x, c, 0]
        m2 += w * hbuf[b, yy, x, c, 1]
        mrq += w * hbuf[b, yy, x, c, 2]
    return m, m2, mrq


@ti.func
def block_moments(hbuf: ti.template(), b, y0, x, c, H):
    """:func:`vertical_moments` at rows [y0, y0 + BLOCK) of column ``x`` (the CPU's vertical passes): M [BLOCK, 3],
    each input row of the block's window loaded once for the rows it reaches; the same taps in the same order.
    Rows past the image get the clamped rows' numbers (for the caller to leave out)."""
    M = ti.Matrix.zero(ti.f32, BLOCK, 3)
    for s in ti.static(range(BLOCK + 2 * RADIUS)):  # input row y0 - RADIUS + s, clamped
        yy = ti.min(ti.max(y0 - RADIUS + s, 0), H - 1)
        h = ti.Vector([hbuf[b, yy, x, c, 0], hbuf[b, yy, x, c, 1], hbuf[b, yy, x, c, 2]])
        for r in ti.static(range(BLOCK)):  # output row y0 + r reads it with tap s - r
            if ti.static(0 <= s - r <= 2 * RADIUS):
                for k in ti.static(range(3)):
                    M[r, k] += ti.static(_W[s - r]) * h[k]
    return M


@ti.func
def cs_of_moments(m, m2, mrq, qstats: ti.template(), qi, y, x, c):
    """The cs term at one pixel and channel from the rendering's windowed r, r^2 and r q against query slot
    ``qi``, ``(2 s_rq + C2) / D`` with ``D = s_rr + s_qq + C2``: returns (cs, D, windowed rendering mean,
    windowed query mean)."""
    mq = qstats[qi, y, x, c, 0]
    s_rr = ti.max(m2 - m * m, 0.0)
    s_rq = mrq - m * mq
    den = s_rr + qstats[qi, y, x, c, 1] + C2
    return (2.0 * s_rq + C2) / den, den, m, mq


@ti.func
def contrast_structure(hbuf: ti.template(), qstats: ti.template(), qi, b, y, x, c, H):
    """:func:`cs_of_moments` at one pixel and channel of pose ``b``, from the horizontal pass ``hbuf``; shared by the
    cost and its derivative (``window_grad.py``)."""
    m, m2, mrq = vertical_moments(hbuf, b, y, x, c, H)
    return cs_of_moments(m, m2, mrq, qstats, qi, y, x, c)


@ti.func
def _no_pixel_outputs(cs, den, m, mq, valid, b, y, x, c, outs: ti.template()):
    pass


def row_sums(value, pixel=_no_pixel_outputs):
    """The vertical pass from the horizontal pass ``hbuf`` [B, H, W, 3, 3] to per-row sums rows [B, H, 1, >= 2]:
    fields 0, 1 = (sum over the row's valid pixels, alpha >= ``mask_alpha``, of the channels' mean of
    ``value(cs, m, mq)``, valid pixels), the run-statistics layout that ``blend.reduce_rows`` sums per pose; and
    ``pixel(cs, den, m, mq, valid, b, y, x, c, outs)`` at every pixel and channel (``outs``: the caller's arrays;
    by default nothing; both ti.funcs). On the CPU one task per ``BLOCK`` rows (:func:`block_moments`), elsewhere one
    per row; each row's sum in the order of its pixels either way. Returns a ti.func ``(hbuf, qstats, query_index,
    alpha, mask_alpha, num_poses, rows, outs)``."""

    @ti.func
    def run(hbuf: ti.template(), qstats: ti.template(), query_index: ti.template(), alpha: ti.template(), mask_alpha,
            num_poses, rows: ti.template(), outs: ti.template()):
        H = hbuf.shape[1]
        W = hbuf.shape[2]
        stride = ti.static(spread())
        nblk = (H + BLOCK - 1) // BLOCK if ti.static(stride > 1) else H
        for task in range(num_poses * nblk * stride):
            is_item, b, blk = item(task, stride, nblk)
            if is_item:
                qi = query_index[b]
                if ti.static(stride > 1):  # the CPU (grain.py): rows [y0, y0 + BLOCK)
                    y0 = blk * BLOCK
                    tot = ti.Vector([0.0] * BLOCK)
                    cnt = ti.Vector([0.0] * BLOCK)
                    for x in range(W):
                        v = ti.Vector([0.0] * BLOCK)
                        for c in range(3):
                            M = block_moments(hbuf, b, y0, x, c, H)
                            for r in ti.static(range(BLOCK)):
                                y = ti.min(y0 + r, H - 1)  # a row past the image: computed, not kept
                                cs, den, m, mq = cs_of_moments(M[r, 0], M[r, 1], M[r, 2], qstats, qi, y, x, c)
                                v[r] += value(cs, m, mq)
                                if y0 + r < H:
                                    pixel(cs, den, m, mq, alpha[b, y, x] >= mask_alpha, b, y, x, c, outs)
                        for r in ti.static(range(BLOCK)):
                            if y0 + r < H:
                                if alpha[b, y0 + r, x] >= mask_alpha:
                                    tot[r] += v[r] / 3.0
                                    cnt[r] += 1.0
                    for r in ti.static(range(BLOCK)):
                        if y0 + r < H:
                            rows[b, y0 + r, 0, 0] = tot[r]
                            rows[b, y0 + r, 0, 1] = cnt[r]
                else:  # one row
                    y = blk
                    tot = 0.0
                    cnt = 0.0
                    for x in range(W):
                        valid = alpha[b, y, x] >= mask_alpha
                        v = 0.0
                        for c in ti.static(range(3)):
                            cs, den, m, mq = contrast_structure(hbuf, qstats, qi, b, y, x, c, H)
                            v += value(cs, m, mq)
                            pixel(cs, den, m, mq, valid, b, y, x, c, outs)
                        if valid:
                            tot += v / 3.0
                            cnt += 1.0
                    rows[b, y, 0, 0] = tot
                    rows[b, y, 0, 1] = cnt

    return run


def vertical_cost(with_luminance: bool):
    """:func:`row_sums` of the per-pixel cs, or with ``with_luminance`` SSIM (cs times the luminance term)."""

    @ti.func
    def value(cs, m, mq):
        v = cs
        if ti.static(with_luminance):
            v *= (2.0 * m * mq + C1) / (m * m + mq * mq + C1)
        return v

    return row_sums(value)


@functools.cache
def window_cost_kernel(config, splat: bool, with_luminance: bool):
    """B poses' windowed similarity in one launch, after their projection and tile sort: the image blend
    (``splat.splat_image_func`` or ``blend.image_func``, its arguments first) into rgb [B, H, W, 3] and alpha
    [B, H, W] (``depth`` is not written: the cost needs none), the horizontal pass into hbuf [B, H, W, 3, 3], the
    vertical pass's per-row sums into rows [B, H, 1, 2], then their totals per pose into ``out`` [B, 2] float64
    (sum of the per-pixel values, valid pixels; a host array: no read-back launch)."""
    blend = splat_image_func(config, depth=False) if splat else image_func(config, depth=False)
    vertical = vertical_cost(with_luminance)
    f32, i32 = ti.f32, ti.i32

    @ti.kernel
    def window_cost(packed: ti.types.ndarray(dtype=f32, ndim=3), tile_start: ti.types.ndarray(dtype=i32, ndim=2),
                    isect: ti.types.ndarray(dtype=i32, ndim=1), isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
                    background: ti.types.ndarray(dtype=f32, ndim=1), tiles_x: i32, tiles_y: i32, num_poses: i32,
                    rgb: ti.types.ndarray(dtype=f32, ndim=4), alpha: ti.types.ndarray(dtype=f32, ndim=3),
                    depth: ti.types.ndarray(dtype=f32, ndim=3), qstats: ti.types.ndarray(dtype=f32, ndim=5),
                    query_index: ti.types.ndarray(dtype=i32, ndim=1), mask_alpha: f32,
                    hbuf: ti.types.ndarray(dtype=f32, ndim=5), rows: ti.types.ndarray(dtype=f32, ndim=4),
                    out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        blend(packed, tile_start, isect, isect_base, background, tiles_x, tiles_y, num_poses, rgb, alpha, depth)
        horizontal(rgb, qstats, query_index, num_poses, hbuf)
        vertical(hbuf, qstats, query_index, alpha, mask_alpha, num_poses, rows, ())
        reduce_rows(rows, num_poses, out)

    return window_cost
