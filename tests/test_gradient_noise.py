"""The cs gradient's covariance under pixel noise (render/gradient_noise.py), the pixel-noise part of a pose's
uncertainty.

References: explicit window matrices for the separable filter and its adjoint; the autograd twin
``tests/reference/render_torch.py::cs_gradient_noise`` for the covariance; and the spread of the Taichi gradient
itself over independent noise draws for what the covariance claims.
"""

from __future__ import annotations

import numpy as np

import hgsloc_plugin as hp
from hgsloc_plugin.kernels.window import RADIUS, window_weights
from hgsloc_plugin.render import get_renderer
from hgsloc_plugin.render.gradient_noise import gradient_noise, window

from .conftest import room_query
from .reference.render_torch import cs_gradient_noise


def _window_matrix(n: int) -> np.ndarray:
    """[n, n]: the window's taps along one axis with clamped (replicated) border coordinates, written out."""
    taps = window_weights()
    m = np.zeros((n, n))
    for i in range(n):
        for j, t in enumerate(taps):
            m[i, min(max(i + j - RADIUS, 0), n - 1)] += t
    return m


def test_window_and_its_adjoint_match_the_written_out_matrices():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(13, 17, 2))
    my, mx = _window_matrix(13), _window_matrix(17)
    np.testing.assert_allclose(window(x), np.einsum("yY,xX,YXc->yxc", my, mx, x), atol=1e-12)
    np.testing.assert_allclose(window(x, adjoint=True), np.einsum("Yy,Xx,YXc->yxc", my, mx, x), atol=1e-12)


def _setup(noise_seed: int | None, mask_alpha: float = 0.0):
    cam = hp.Camera(64, 48, 56.0, 56.0, 32.0, 24.0)
    scene, gt, img, _ = room_query(cam, pose_seed=1, noise_deg=0.0, noise_shift=0.0, noise_seed=0)
    r = get_renderer(scene)
    if noise_seed is not None:
        img = np.clip(img + np.random.default_rng(noise_seed).normal(scale=0.02, size=img.shape), 0, 1)
    return cam, gt, r, img.astype(np.float32)


def _covariance(r, cam, pose, qstats, mask_alpha=0.0):
    rgb, alpha, drgb = r.render_derivatives(cam, [pose])
    return gradient_noise(rgb[0], alpha[0], drgb[0], qstats.to_numpy()[0], mask_alpha), (rgb[0], alpha[0], drgb[0])


def test_gradient_noise_matches_its_autograd_twin():
    """On a room render with a noisy query and some pixels masked out, the covariance from the Taichi renderer's
    derivative images and query statistics equals the twin's from the same images, and the renderer's
    ``pose_gradient_noise`` (the rule's one derivative pass) gives it with the Hessian of ``pose_gradient``."""
    cam, gt, r, img = _setup(noise_seed=3)
    qstats = r.upload_window_query(img)
    cov, (rgb, alpha, drgb) = _covariance(r, cam, gt, qstats, mask_alpha=0.99)
    valid = alpha >= 0.99
    assert 0.1 < 1 - valid.mean() < 0.9  # the mask (alpha >= 0.99) matters
    twin = cs_gradient_noise(rgb, img, drgb, valid)
    np.testing.assert_allclose(cov, twin, rtol=1e-5, atol=1e-5 * np.abs(twin).max())
    hess, bands, noise = r.pose_gradient_noise(cam, gt, qstats, mask_alpha=0.99)
    _, grad, hess_full = r.pose_gradient(cam, [gt], qstats, mask_alpha=0.99)
    np.testing.assert_allclose(noise, cov, rtol=1e-9)
    np.testing.assert_allclose(hess, hess_full[0], rtol=1e-9)
    np.testing.assert_allclose(bands.sum(0), grad[0], rtol=1e-5, atol=1e-9)


def test_gradient_noise_predicts_the_gradients_spread_over_noise_draws():
    """At the true pose, 48 queries with independent pixel noise: the covariance the estimator gives from each
    single query, averaged, is the Taichi gradient's own spread over the draws within a factor 1.6 in the trace
    of each block (the rule's band sandwich is 4-6x on the room: ``benchmarks/sigma.md``)."""
    cam, gt, r, clean = _setup(noise_seed=None)
    grads, covs = [], []
    for seed in range(48):
        img = np.clip(clean + np.random.default_rng(100 + seed).normal(scale=0.02, size=clean.shape), 0, 1)
        qstats = r.upload_window_query(img.astype(np.float32))
        _, g, _ = r.pose_gradient(cam, [gt], qstats)
        grads.append(g[0])
        covs.append(_covariance(r, cam, gt, qstats)[0])
    spread = np.cov(np.array(grads).T)
    predicted = np.mean(covs, axis=0)
    for block in (slice(0, 3), slice(3, 6)):
        ratio = np.trace(predicted[block, block]) / np.trace(spread[block, block])
        assert 1 / 1.6 < ratio < 1.6, ratio
