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
