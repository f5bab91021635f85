"""Gradient and Gauss-Newton Hessian of the ``cs`` cost with respect to the pose, from the derivative images.

The cost (``kernels/window.py``) is ``1 - mean cs`` over valid pixels p and channels c. Per pixel and channel,
with d = r - q and the window weights w_pk (separable Gaussian, clamped border):

    1 - cs_p = N_p / D_p,   N_p = s_rr + s_qq - 2 s_rq = sum_k w_pk (d_k - dbar_p)^2,   D_p = s_rr + s_qq + C2

so the cost is a weighted least-squares sum of the windowed zero-mean difference, with the per-pixel weight
1 / D_p: the iteratively reweighted least-squares (IRLS) form. With the derivative images J_k = dr_k / dxi
[6] (``pose_grad.blend_grad``) and their windowed means Jbar_p:

    dN_p = 2 (sum_k w_pk d_k J_k - dbar_p Jbar_p),   dD_p = 2 (sum_k w_pk r_k J_k - m_p Jbar_p)
    grad = 1/(3n) sum_pc (dN_p / D_p - N_p dD_p / D_p^2)                         (exact gradient of the cost)
    JtJ  = 1/(3n) sum_pc 2 (sum_k w_pk J_k J_k^T - Jbar_p Jbar_p^T) max(cs_p, 0) / D_p       (Gauss-Newton)

As N'' = D'' (both 2 (sum_k w_pk J_k J_k^T - Jbar_p Jbar_p^T) without the render's second derivatives), the
Hessian of N_p / D_p is N'' (1 / D_p - N_p / D_p^2) = N'' cs_p / D_p plus rank-two terms in dN_p and dD_p,
which JtJ drops; cs_p is clamped at 0 so that JtJ stays positive semi-definite. JtJ is the exact Hessian at a
zero residual (cs_p = 1, N_p = 0, dN_p = 0). The sums over k of per-pixel weights are regrouped with the window's
transpose: ``sum_p A_p sum_k w_pk X_k = sum_k X_k (W^T A)_k``, so only scalar weight images are
filtered (``window_filter(transpose=True)``) and the 6x6 products are formed once per pixel.
Everything stays on the device (one launch, ``cs_system_kernel``); rows are summed per pose in float64 by
``blend.reduce_rows`` (fixed order).
Reference twin: ``tests/test_pose_grad.py`` (central differences of the Taichi cost).
"""

import functools

import taichi as ti

from .blend import reduce_rows
from .grain import item, spread
from .pose_grad import NXI
from .window import BLOCK, RADIUS, horizontal, row_sums, window_weights

_W = window_weights()

NH = NXI * (NXI + 1) // 2  # upper triangle of JtJ, row-major
NW = 9  # per-pixel weight channels: (1 / D, N / D^2) per colour channel, then max(cs, 0) / D per channel
NSYS = NH + NXI  # per-row record: JtJ triangle, then the gradient
ROW_SYS = 2  # in the per-row sums [B, H, 1, ROW_SYS + NSYS]: cs_terms' two, then the system's (one reduction)
_CUM = [sum(_W[:m + 1]) for m in range(2 * RADIUS + 1)]  # sum_{j <= m} w_j
_TAIL = [sum(_W[m:]) for m in range(2 * RADIUS + 1)]  # sum_{j >= m} w_j
_WINDOW_ROWS = list(range(BLOCK + 2 * RADIUS))  # the input rows of a block of output rows


@ti.func
def _pixel_weights(cs, den, m, mq, valid, b, y, x, c, outs: ti.template()):
    """:func:`cs_terms`' outputs ``outs`` = (weights, means) at one pixel and channel from its cs term."""
    a = 0.0
    bw = 0.0
    gw = 0.0
    if valid:
        a = 1.0 / den
        bw = (1.0 - cs) / den
        gw = ti.max(cs, 0.0) / den
    outs[0][b, y, x, 2 * c] = a
    outs[0][b, y, x, 2 * c + 1] = bw
    outs[0][b, y, x, 6 + c] = gw
    outs[1][b, y, x, 2 * c] = m
    outs[1][b, y, x, 2 * c + 1] = m - mq


@ti.func
def _cs(cs, m, mq):
    return cs


#: Per pixel and channel, from the rendering's horizontal window pass (``window.horizontal``): weights [B, H, W,
#: NW] (A = 1/D, B = N/D^2 per channel c at 2c, 2c + 1; G = max(cs, 0) / D at 6 + c; 0 on invalid pixels), means
#: [B, H, W, 6] (m_r, dbar = m_r - m_q per channel), passed as ``outs``, and rows [B, H, 1, >= 2]: fields 0, 1 =
#: (sum of the channel-mean cs, valid pixels), the same numbers as ``window.vertical_cost(False)``
#: (``window.row_sums``).
cs_terms = row_sums(_cs, _pixel_weights)


@functools.cache
def window_filter(axis: int, transpose: bool, channels: int):
    """One separable pass of the window over images [B, H, W, channels] along ``axis`` (0: columns, along y; 1:
    rows, along x), border coordinates clamped as in ``window.py``; ``transpose``: the pass's transpose (what each
    input pixel gives to the outputs: at the borders the clamped taps' weights add up). On the CPU (``grain.py``)
    a row pass runs one task per row, its taps sliding along the row in registers (:func:`slide`), a column pass
    one task per ``BLOCK`` rows (:func:`column_block`), each loading an input once for the outputs it reaches;
    elsewhere one task per pixel (:func:`at`): the same sums to float32 rounding."""

    @ti.func
    def get(src: ti.template(), b, line, pos, c):
        """Channel ``c`` at position ``pos`` along the pass of line ``line``: row ``line``'s x for axis 1, column
        ``line``'s y for axis 0."""
        v = 0.0
        if ti.static(axis == 1):
            v = src[b, line, pos, c]
        else:
            v = src[b, pos, line, c]
        return v

    @ti.func
    def put(dst: ti.template(), b, line, pos, c, v):
        if ti.static(axis == 1):
            dst[b, line, pos, c] = v
        else:
            dst[b, pos, line, c] = v

    @ti.func
    def border(src: ti.template(), b, line, pos, L, c):
        """The transposed pass at a line's first or last position (``pos`` 0 or L - 1), where taps clamp."""
        acc = 0.0
        if L == 1:
            acc = get(src, b, line, 0, c)
        elif pos == 0:  # every tap that clamps to 0: from q <= RADIUS, taps j <= RADIUS - q
            for q in ti.static(range(RADIUS + 1)):
                if q < L:
                    acc += ti.static(_CUM[RADIUS - q]) * get(src, b, line, q, c)
        else:  # taps that clamp to L - 1: from q = L - 1 - s, taps j >= s + RADIUS
            for s in ti.static(range(RADIUS + 1)):
                q = L - 1 - s
                if q >= 0:
                    acc += ti.static(_TAIL[s + RADIUS]) * get(src, b, line, q, c)
        return acc

    @ti.func
    def load(src: ti.template(), b, line, pos):
        v = ti.Vector([0.0] * channels)
        for c in ti.static(range(channels)):
            v[c] = get(src, b, line, pos, c)
        return v

    @ti.func
    def at(src: ti.template(), b, line, pos, L, dst: ti.template()):
        """The pass at one pixel, every channel at each tap."""
        acc = ti.Vector([0.0] * channels)
        if ti.static(not transpose):
            for j in ti.static(range(2 * RADIUS + 1)):
                acc += ti.static(_W[j]) * load(src, b, line, ti.min(ti.max(pos + j - RADIUS, 0), L - 1))
        elif pos == 0 or pos == L - 1:
            for c in ti.static(range(channels)):
                acc[c] = border(src, b, line, pos, L, c)
        else:
            for j in ti.static(range(2 * RADIUS + 1)):
                q = pos - j + RADIUS
                if 0 <= q and q < L:
                    acc += ti.static(_W[j]) * load(src, b, line, q)
        for c in ti.static(range(channels)):
            put(dst, b, line, pos, c, acc[c])

    @ti.func
    def slide(src: ti.template(), b, line, L, dst: ti.template()):
        """The pass along one line of L pixels (the CPU's rows), channel by channel: ``v[k]`` holds the input at
        ``pos - RADIUS + k`` (clamped; for the transpose 0 outside the line, whose ends take :func:`border`). The
        channels are a run-time loop: one copy of the code, not one a channel (compile time)."""
        for c in range(channels):
            v = ti.Vector([0.0] * (2 * RADIUS + 1))
            for k in ti.static(range(2 * RADIUS + 1)):
                if ti.static(not transpose):
                    v[k] = get(src, b, line, ti.min(ti.max(k - RADIUS, 0), L - 1), c)
                elif ti.static(k >= RADIUS):
                    if k - RADIUS < L:
                        v[k] = get(src, b, line, k - RADIUS, c)
            for pos in range(L):
                acc = 0.0
                if ti.static(not transpose):
                    for j in ti.static(range(2 * RADIUS + 1)):
                        acc += ti.static(_W[j]) * v[j]
                elif pos == 0 or pos == L - 1:
                    acc = border(src, b, line, pos, L, c)
                else:  # tap j of output pos reads input pos - j + RADIUS
                    for j in ti.static(range(2 * RADIUS + 1)):
                        acc += ti.static(_W[j]) * v[2 * RADIUS - j]
                put(dst, b, line, pos, c, acc)
                for k in ti.static(range(2 * RADIUS)):
                    v[k] = v[k + 1]
                nxt = pos + RADIUS + 1
                if ti.static(not transpose):
                    v[2 * RADIUS] = get(src, b, line, ti.min(nxt, L - 1), c)
                else:
                    v[2 * RADIUS] = get(src, b, line, ti.min(nxt, L - 1), c) if nxt < L else 0.0

    @ti.func
    def column_block(src: ti.template(), b, y0, H, W, dst: ti.template()):
        """The column pass at rows [y0, y0 + BLOCK) of every column (the CPU's): each input row of the block's
        window is loaded once for the BLOCK outputs it reaches (``BLOCK + 2 RADIUS`` loads a column and channel
        instead of ``11 BLOCK``); the same taps in the same order as :func:`at`. The transpose takes 0 outside the
        image here: its first and last rows are :func:`border`'s (``filt`` writes them after)."""
        for x in range(W):
            for c in range(channels):
                acc = ti.Vector([0.0] * BLOCK)
                for s in ti.static(_WINDOW_ROWS if not transpose else _WINDOW_ROWS[::-1]):
                    q = y0 - RADIUS + s  # input row s of the block's window
                    v = get(src, b, x, ti.min(ti.max(q, 0), H - 1), c)
                    if ti.static(transpose):
                        v = ti.select(0 <= q and q < H, v, 0.0)
                    for r in ti.static(range(BLOCK)):  # output row y0 + r: its tap s - r (transposed: the mirror)
                        if ti.static(0 <= s - r <= 2 * RADIUS):
                            acc[r] += ti.static(_W[s - r] if not transpose else _W[2 * RADIUS - (s - r)]) * v
                for r in ti.static(range(BLOCK)):
                    if y0 + r < H:
                        put(dst, b, x, y0 + r, c, acc[r])

    @ti.func
    def filt(src: ti.template(), num_poses, dst: ti.template()):
        H = src.shape[1]
        W = src.shape[2]
        stride = ti.static(spread())
        nblk = (H + BLOCK - 1) // BLOCK
        if ti.static(stride > 1 and axis == 0):  # the CPU: one task per block of rows
            for task in range(num_poses * nblk * stride):
                is_item, b, blk = item(task, stride, nblk)
                if is_item:
                    column_block(src, b, blk * BLOCK, H, W, dst)
            if ti.static(transpose):  # the first and last rows, where the transposed taps clamp
                for task in range(num_poses * 2 * stride):
                    is_item, b, end = item(task, stride, 2)
                    if is_item:
                        y = end * (H - 1)
                        for x in range(W):
                            for c in range(channels):
                                put(dst, b, x, y, c, border(src, b, x, y, H, c))
        elif ti.static(stride > 1):  # the CPU: one task per image row (grain.py)
            for task in range(num_poses * H * stride):
                is_item, b, y = item(task, stride, H)
                if is_item:
                    slide(src, b, y, W, dst)
        else:
            for b, y, x in ti.ndrange(num_poses, H, W):
                if ti.static(axis == 1):
                    at(src, b, y, x, W, dst)
                else:
                    at(src, b, x, y, H, dst)

    return filt


@ti.func
def system(rgb: ti.template(), qstats: ti.template(), query_index: ti.template(), drgb: ti.template(),
           jbar: ti.template(), weights: ti.template(), what: ti.template(), means: ti.template(), num_poses,
           rows: ti.template()):
    """Per-row sums of the JtJ triangle and the gradient, unscaled (``2 / (3 n)`` is applied by the caller):
    rows [B, H, 1, ROW_SYS + NSYS], fields from ``ROW_SYS`` on (the first are ``cs_terms``').

    Inputs: rgb [B, H, W, 3], qstats [Q, H, W, 3, NQ] (the query pixel is field 2) read at slot
    query_index [B], drgb and its windowed mean
    jbar [B, H, W, 3 * 6], weights and their transposed window what [B, H, W, NW], means [B, H, W, 6].
    """

    H = rgb.shape[1]
    W = rgb.shape[2]
    stride = ti.static(spread())  # one task per image row on the CPU (grain.py)
    for task in range(num_poses * H * stride):
        is_item, b, y = item(task, stride, H)
        if is_item:
            qi = query_index[b]
            acc = ti.Vector([0.0] * NSYS)
            for x in range(W):
                for c in ti.static(range(3)):
                    Jk = ti.Vector([drgb[b, y, x, c * NXI + j] for j in ti.static(range(NXI))])
                    Jb = ti.Vector([jbar[b, y, x, c * NXI + j] for j in ti.static(range(NXI))])
                    ah = what[b, y, x, 2 * c]
                    bh = what[b, y, x, 2 * c + 1]
                    a = weights[b, y, x, 2 * c]
                    bw = weights[b, y, x, 2 * c + 1]
                    r = rgb[b, y, x, c]
                    d = r - qstats[qi, y, x, c, 2]
                    gh = what[b, y, x, 6 + c]
                    gw = weights[b, y, x, 6 + c]
                    gk = (d * ah - r * bh) * Jk - (a * means[b, y, x, 2 * c + 1] - bw * means[b, y, x, 2 * c]) * Jb
                    for i in ti.static(range(NXI)):
                        for j in ti.static(range(i, NXI)):
                            idx = ti.static(i * NXI - i * (i - 1) // 2 + (j - i))
                            acc[idx] += gh * Jk[i] * Jk[j] - gw * Jb[i] * Jb[j]
                        acc[NH + i] += gk[i]
            for s in ti.static(range(NSYS)):
                rows[b, y, 0, ROW_SYS + s] = acc[s]


@functools.cache
def cs_system_kernel():
    """The cs cost's Gauss-Newton system of B poses in one launch, from their renderings rgb [B, H, W, 3], alpha
    [B, H, W] and colour derivatives drgb [B, H, W, 3 * NXI] against the query statistics at ``query_index``:
    the horizontal window pass (into h), the per-pixel terms (weights, means, the cs sums into rows' fields 0-1),
    the windowed derivatives (tmpj, jbar) and the transposed window of the weights (tmpw, what), the rows of
    the JtJ triangle and the gradient (rows' fields from ``ROW_SYS``), then every field summed per pose into
    ``out`` [B, ROW_SYS + NSYS] float64 (a host array: no read-back launch). Scratch shapes: ``WindowGradBuffers``.
    """
    rows_of_drgb, cols_of_jbar = window_filter(1, False, 3 * NXI), window_filter(0, False, 3 * NXI)
    cols_of_weights, rows_of_what = window_filter(0, True, NW), window_filter(1, True, NW)
    f32 = ti.f32

    @ti.kernel
    def cs_system(rgb: ti.types.ndarray(dtype=f32, ndim=4), alpha: ti.types.ndarray(dtype=f32, ndim=3),
                  drgb: ti.types.ndarray(dtype=f32, ndim=4), qstats: ti.types.ndarray(dtype=f32, ndim=5),
                  query_index: ti.types.ndarray(dtype=ti.i32, ndim=1), mask_alpha: f32, num_poses: ti.i32,
                  h: ti.types.ndarray(dtype=f32, ndim=5), weights: ti.types.ndarray(dtype=f32, ndim=4),
                  means: ti.types.ndarray(dtype=f32, ndim=4), tmpj: ti.types.ndarray(dtype=f32, ndim=4),
                  jbar: ti.types.ndarray(dtype=f32, ndim=4), tmpw: ti.types.ndarray(dtype=f32, ndim=4),
                  what: ti.types.ndarray(dtype=f32, ndim=4), rows: ti.types.ndarray(dtype=f32, ndim=4),
                  out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        horizontal(rgb, qstats, query_index, num_poses, h)
        cs_terms(h, qstats, query_index, alpha, mask_alpha, num_poses, rows, (weights, means))
        rows_of_drgb(drgb, num_poses, tmpj)
        cols_of_jbar(tmpj, num_poses, jbar)
        cols_of_weights(weights, num_poses, tmpw)
        rows_of_what(tmpw, num_poses, what)
        system(rgb, qstats, query_index, drgb, jbar, weights, what, means, num_poses, rows)
        reduce_rows(rows, num_poses, out)

    return cs_system
