"""Kernel launches through a ``Launcher`` (``kernels/launch.py``): after Taichi's own first call of an argument
signature, the fast path sets each call's own arguments (new arrays, new scalars) and gives Taichi's results; what
it does not cover keeps Taichi's path, checks included.

No ``from __future__ import annotations`` here: Taichi reads the kernel annotations as objects."""

import numpy as np
import pytest
import taichi as ti

import hgsloc_plugin as hp
from hgsloc_plugin.kernels import launch


@pytest.fixture(scope="module")
def kernels():
    hp.init()

    @ti.kernel
    def affine(src: ti.types.ndarray(dtype=ti.f32, ndim=2), scale: ti.f32, shift: ti.i32, offset: ti.u32,
               out: ti.types.ndarray(dtype=ti.f64, ndim=2)):
        for i, j in ti.ndrange(src.shape[0], src.shape[1]):
            out[i, j] = src[i, j] * scale + shift + ti.cast(offset, ti.f32)

    @ti.kernel
    def fill(dst: ti.types.ndarray(), value: ti.f32):  # no dtype: one compiled kernel per array type
        for i in ti.grouped(dst):
            dst[i] = value

    @ti.kernel
    def twice(n: ti.template(), dst: ti.types.ndarray(dtype=ti.f32, ndim=1)):
        for i in range(n):
            dst[i] = 2.0 * i

    return affine, fill, twice


def _plans(kernel):
    return launch.launcher(kernel).plans


def test_fast_path_sets_each_calls_own_arguments(kernels):
    affine = kernels[0]
    fast = launch.launcher(affine)
    rng = np.random.default_rng(0)
    for k in range(4):  # the first call through Taichi, the rest on the fast path
        src_host = rng.random((5, 7), dtype=np.float32)
        src = ti.ndarray(ti.f32, (5, 7))
        src.from_numpy(src_host)
        out = np.zeros((5, 7), np.float64)  # a new host array each call: its own address
        fast(src, 0.5 + k, 3 - k, 10 * k, out)
        expected = np.zeros_like(out)
        affine(src, 0.5 + k, 3 - k, 10 * k, expected)
        np.testing.assert_array_equal(out, expected)
        assert np.allclose(out, src_host * (0.5 + k) + (3 - k) + 10 * k)
    assert [p is not None for p in _plans(affine).values()] == [True]


def test_each_signature_gets_taichis_checks(kernels):
    affine, fill = kernels[0], kernels[1]
    fast = launch.launcher(fill)
    for dtype, ti_dtype in ((np.float32, ti.f32), (np.int32, ti.i32)):
        for _ in range(2):
            host = np.zeros((3, 4), dtype)
            fast(host, 7.0)
            np.testing.assert_array_equal(host, np.full((3, 4), 7, dtype))
            dev = ti.ndarray(ti_dtype, (6,))
            fast(dev, 3.0)
            np.testing.assert_array_equal(dev.to_numpy(), np.full(6, 3, dtype))
    assert len(_plans(fill)) == 4 and all(p is not None for p in _plans(fill).values())
    src = ti.ndarray(ti.f32, (2, 2))
    launch.launcher(affine)(src, 1.0, 0, 0, np.zeros((2, 2), np.float64))
    with pytest.raises(ValueError, match="dtype"):  # a host array of the wrong dtype: a new signature, refused
        launch.launcher(affine)(src, 1.0, 0, 0, np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="ndim"):  # the wrong rank
        launch.launcher(affine)(src, 1.0, 0, 0, np.zeros(4, np.float64))


def test_uncovered_arguments_keep_taichis_path(kernels):
    fill, twice = kernels[1], kernels[2]
    dst = ti.ndarray(ti.f32, (8,))
    for n in (3, 5):
        launch.launcher(twice)(n, dst)
    assert set(_plans(twice).values()) == {None}  # a template argument
    np.testing.assert_array_equal(dst.to_numpy()[:5], 2.0 * np.arange(5))
    strided = np.zeros((4, 6), np.float32)[:, ::2]  # not contiguous: Taichi refuses it, as without the launcher
    with pytest.raises(ValueError):
        launch.launcher(fill)(strided, 1.0)


def test_upload_equals_from_numpy(kernels):
    values = np.arange(24, dtype=np.float64).reshape(2, 3, 4) / 7.0
    a = ti.ndarray(ti.f32, (2, 3, 4))
    b = ti.ndarray(ti.f32, (2, 3, 4))
    for k in range(2):
        launch.upload(a, values + k)
        b.from_numpy(values + k)
        np.testing.assert_array_equal(a.to_numpy(), b.to_numpy())
    with pytest.raises(ValueError, match="shape"):
        launch.upload(a, values[0])


def test_empty_arrays_work_as_taichis_and_keep_their_own_memory(kernels):
    """``launch.empty``: a scalar ndarray of the shape and element type asked, usable on the fast path and on
    Taichi's, each with its own memory (a write to one leaves another intact), freed with its object; a bad shape
    is refused as by ``ti.ndarray``."""
    affine, fill = kernels[0], kernels[1]
    rng = np.random.default_rng(1)
    for k in range(3):
        src = launch.empty(ti.f32, (5, 7))
        assert isinstance(src, ti.Ndarray) and src.shape == (5, 7) and src.dtype == ti.f32
        host = rng.random((5, 7), dtype=np.float32)
        launch.upload(src, host)
        other = launch.empty(ti.f32, (5, 7))
        launch.launcher(fill)(other, float(k))
        out = np.zeros((5, 7), np.float64)
        launch.launcher(affine)(src, 2.0, 1, 0, out)  # through a Launcher: the second call on its fast path
        np.testing.assert_array_equal(out, (host * np.float32(2.0) + np.float32(1.0)).astype(np.float64))
        np.testing.assert_array_equal(src.to_numpy(), host)
        np.testing.assert_array_equal(other.to_numpy(), np.full((5, 7), k, np.float32))
    ints = launch.empty(ti.i32, (3,))
    assert ints.dtype == ti.i32 and ints.shape == (3,)
    with pytest.raises(Exception, match="not a valid shape"):
        launch.empty(ti.f32, (0, 4))
