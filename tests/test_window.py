"""The window's separable passes (``kernels/window.py``: the query statistics and ``horizontal``;
``kernels/window_grad.py::window_filter``) against NumPy twins in float64, on image sizes from one pixel to a few
windows, where the CPU's sliding passes meet both borders at once; in both layouts: the CPU's (one task per row)
and the GPU's (one per pixel, compiled here on the CPU with ``spread`` patched to 1).

No ``from __future__ import annotations`` here: Taichi reads the kernel annotations as objects."""

import functools

import numpy as np
import pytest
import taichi as ti

import hgsloc_plugin as hp
from hgsloc_plugin.kernels import window, window_grad
from hgsloc_plugin.kernels.window import NQ, RADIUS, window_weights

SIZES = [(1, 1), (1, 4), (3, 7), (12, 2), (6, 11), (5, 12), (13, 17), (4, 40)]


def window_matrix(length: int) -> np.ndarray:
    """M [L, L]: the window along one axis of ``length`` pixels, border coordinates clamped (out = M @ in)."""
    w = window_weights()
    m = np.zeros((length, length))
    for p in range(length):
        for j in range(2 * RADIUS + 1):
            m[p, min(max(p + j - RADIUS, 0), length - 1)] += w[j]
    return m


@pytest.fixture(params=["rows", "pixels"])
def layout(request, monkeypatch):
    """The layout the kernels compile for: the CPU's, or the GPU's one task per pixel."""
    if request.param == "pixels":
        monkeypatch.setattr(window, "spread", lambda: 1)
        monkeypatch.setattr(window_grad, "spread", lambda: 1)
    return request.param


@functools.cache
def filter_kernel(layout: str, axis: int, transpose: bool, channels: int):
    hp.init()
    filt = window_grad.window_filter.__wrapped__(axis, transpose, channels)  # not the cached one: per layout

    @ti.kernel
    def run(src: ti.types.ndarray(dtype=ti.f32, ndim=4), num_poses: ti.i32,
            dst: ti.types.ndarray(dtype=ti.f32, ndim=4)):
        filt(src, num_poses, dst)

    return run


@functools.cache
def horizontal_kernel(layout: str):
    hp.init()
    horizontal = window.horizontal

    @ti.kernel
    def run(rgb: ti.types.ndarray(dtype=ti.f32, ndim=4), qstats: ti.types.ndarray(dtype=ti.f32, ndim=5),
            query_index: ti.types.ndarray(dtype=ti.i32, ndim=1), num_poses: ti.i32,
            out: ti.types.ndarray(dtype=ti.f32, ndim=5)):
        horizontal(rgb, qstats, query_index, num_poses, out)

    return run


@pytest.mark.parametrize("h, w", SIZES)
@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize("transpose", [False, True])
def test_window_filter_is_the_clamped_window_or_its_transpose(layout, h, w, axis, transpose):
    channels = 9 if transpose else 18  # as the cs system filters them: the weights' and the derivatives'
    src = np.random.default_rng(h * 100 + w).normal(size=(2, h, w, channels)).astype(np.float32)
    dst = np.full_like(src, np.nan)
    filter_kernel(layout, axis, transpose, channels)(src, 2, dst)
    m = window_matrix(src.shape[1 + axis])
    if transpose:
        m = m.T
    ref = np.einsum("pq,bqxc->bpxc", m, src) if axis == 0 else np.einsum("pq,byqc->bypc", m, src)
    np.testing.assert_allclose(dst, ref, rtol=0, atol=2e-6 * np.abs(src).max())


@pytest.mark.parametrize("h, w", SIZES)
def test_horizontal_pass_filters_the_rendering_its_square_and_its_product_with_the_query(layout, h, w):
    rng = np.random.default_rng(h * 100 + w)
    rgb = rng.uniform(size=(3, h, w, 3)).astype(np.float32)
    qstats = rng.uniform(size=(2, h, w, 3, NQ)).astype(np.float32)
    query_index = np.array([1, 0, 1], np.int32)
    out = np.full((3, h, w, 3, 3), np.nan, np.float32)
    horizontal_kernel(layout)(rgb, qstats, query_index, 3, out)
    m = window_matrix(w)
    r = rgb.astype(np.float64)
    q = qstats[query_index, ..., 2].astype(np.float64)
    for k, field in enumerate([r, r * r, r * q]):
        np.testing.assert_allclose(out[..., k], np.einsum("pq,byqc->bypc", m, field), rtol=0, atol=2e-6)


@functools.cache
def query_stats_kernel(layout: str):
    hp.init()
    return window.query_stats_kernel.__wrapped__()  # not the cached one: per layout


@pytest.mark.parametrize("h, w", SIZES)
def test_query_statistics_are_the_windowed_mean_and_variance(layout, h, w):
    q = np.random.default_rng(h * 100 + w).uniform(size=(h, w, 3)).astype(np.float32)
    out = np.full((2, h, w, 3, NQ), np.nan, np.float32)
    tmp = np.full((h, w, 3, 2), np.nan, np.float32)
    query_stats_kernel(layout)(q, 1, tmp, out)
    my, mx = window_matrix(h), window_matrix(w)
    q64 = q.astype(np.float64)
    mean = np.einsum("pq,qxc->pxc", my, np.einsum("pq,yqc->ypc", mx, q64))
    second = np.einsum("pq,qxc->pxc", my, np.einsum("pq,yqc->ypc", mx, q64 * q64))
    np.testing.assert_allclose(out[1, ..., 0], mean, rtol=0, atol=2e-6)
    np.testing.assert_allclose(out[1, ..., 1], np.maximum(second - mean * mean, 0.0), rtol=0, atol=4e-6)
    np.testing.assert_array_equal(out[1, ..., 2], q)
    assert np.isnan(out[0]).all()  # the other slot untouched


def window_cost_rows(rgb, alpha, query, mask_alpha, luminance):
    """Float64 twin of the window cost's per-row sums [B, H, 2] (the cs or SSIM mean over channels of each
    valid pixel, valid pixels) with the clamped window, from renderings rgb [B, H, W, 3] and the query [H, W, 3]."""
    from hgsloc_plugin.kernels.window import C1, C2

    _, h, w, _ = rgb.shape
    my, mx = window_matrix(h), window_matrix(w)

    def filt(a):
        return np.einsum("pq,...qxc->...pxc", my, np.einsum("pq,...yqc->...ypc", mx, a))

    r, q = rgb.astype(np.float64), query.astype(np.float64)
    m, mq = filt(r), filt(q)
    s_rr = np.maximum(filt(r * r) - m * m, 0.0)
    s_qq = np.maximum(filt(q * q) - mq * mq, 0.0)
    value = (2.0 * (filt(r * q) - m * mq) + C2) / (s_rr + s_qq + C2)
    if luminance:
        value *= (2.0 * m * mq + C1) / (m * m + mq * mq + C1)
    valid = alpha >= mask_alpha
    per_pixel = np.where(valid, value.mean(-1), 0.0)
    return np.stack([per_pixel.sum(-1), valid.sum(-1)], -1)


@functools.cache
def window_rows_kernel(layout: str, luminance: bool):
    hp.init()
    vertical = window.vertical_cost(luminance)
    horizontal = window.horizontal

    @ti.kernel
    def run(rgb: ti.types.ndarray(dtype=ti.f32, ndim=4), alpha: ti.types.ndarray(dtype=ti.f32, ndim=3),
            qstats: ti.types.ndarray(dtype=ti.f32, ndim=5), query_index: ti.types.ndarray(dtype=ti.i32, ndim=1),
            mask_alpha: ti.f32, num_poses: ti.i32, hbuf: ti.types.ndarray(dtype=ti.f32, ndim=5),
            rows: ti.types.ndarray(dtype=ti.f32, ndim=4)):
        horizontal(rgb, qstats, query_index, num_poses, hbuf)
        vertical(hbuf, qstats, query_index, alpha, mask_alpha, num_poses, rows, ())

    return run


@pytest.mark.parametrize("h, w", [(1, 4), (5, 12), (13, 17), (17, 9)])
@pytest.mark.parametrize("luminance, mask_alpha", [(False, 0.0), (True, 0.5)])
def test_window_cost_rows_are_the_windowed_cs_of_each_row(layout, h, w, luminance, mask_alpha):
    rng = np.random.default_rng(h * 100 + w)
    rgb = rng.uniform(size=(2, h, w, 3)).astype(np.float32)
    alpha = rng.uniform(size=(2, h, w)).astype(np.float32)
    query = rng.uniform(size=(h, w, 3)).astype(np.float32)
    qstats = np.zeros((1, h, w, 3, NQ), np.float32)
    query_stats_kernel(layout)(query, 0, np.zeros((h, w, 3, 2), np.float32), qstats)
    rows = np.full((2, h, 1, 2), np.nan, np.float32)
    window_rows_kernel(layout, luminance)(rgb, alpha, qstats, np.zeros(2, np.int32), mask_alpha, 2,
                                          np.zeros((2, h, w, 3, 3), np.float32), rows)
    ref = window_cost_rows(rgb, alpha, query, mask_alpha, luminance)
    np.testing.assert_array_equal(rows[:, :, 0, 1], ref[..., 1])
    np.testing.assert_allclose(rows[:, :, 0, 0], ref[..., 0], rtol=0, atol=2e-4 * w)


def test_cs_system_is_the_same_in_both_layouts(monkeypatch):
    """The cs system's kernel (its cs terms in blocks of rows on the CPU, per row elsewhere; the filters' layouts
    above) gives the same sums in both layouts, to float32 rounding."""
    from hgsloc_plugin.kernels.pose_grad import NXI

    b, h, w = 2, 19, 23
    rng = np.random.default_rng(5)
    rgb = rng.uniform(size=(b, h, w, 3)).astype(np.float32)
    alpha = rng.uniform(size=(b, h, w)).astype(np.float32)
    drgb = rng.normal(size=(b, h, w, 3 * NXI)).astype(np.float32)
    qstats = np.zeros((1, h, w, 3, NQ), np.float32)
    query_stats_kernel("rows")(rng.uniform(size=(h, w, 3)).astype(np.float32), 0, np.zeros((h, w, 3, 2), np.float32),
                               qstats)
    nw, k = window_grad.NW, window_grad.ROW_SYS + window_grad.NSYS
    outs = []
    for layout in ("rows", "pixels"):
        if layout == "pixels":
            monkeypatch.setattr(window, "spread", lambda: 1)
            monkeypatch.setattr(window_grad, "spread", lambda: 1)
        scratch = [np.zeros(s, np.float32) for s in [(b, h, w, 3, 3), (b, h, w, nw), (b, h, w, 6), (b, h, w, 3 * NXI),
                                                     (b, h, w, 3 * NXI), (b, h, w, nw), (b, h, w, nw), (b, h, 1, k)]]
        out = np.zeros((b, k), np.float64)
        hp.init()
        window_grad.cs_system_kernel.__wrapped__()(rgb, alpha, drgb, qstats, np.zeros(b, np.int32), 0.3, b, *scratch,
                                                   out)
        outs.append(out)
    np.testing.assert_array_equal(outs[0][:, 1], outs[1][:, 1])  # valid pixels
    np.testing.assert_allclose(outs[0], outs[1], rtol=2e-5, atol=1e-6 * np.abs(outs[1]).max())
