"""The cs gradient's covariance under independent noise in the query's pixels, from one derivative pass: the
image's part of the sigma a polished pose is returned with (``refine/uncertainty.py``; the rule itself weighs
by the band sandwich).

The cs cost (``kernels/window_grad.py``) is ``1/(3n) sum_pc N_p / D_p``. Its gradient in the pose increment
``xi`` is ``1/(3n) sum_pc (dN_p / D_p - N_p dD_p / D_p^2)``; the first part is linear in the query q (with
``D_p`` held), the second is of the order of the residual ``N_p`` and is left out. A change ``dq_k`` of query
pixel k and channel c moves the first part by ``a_k dq_k``, with the influence

    a_k = -2/(3n) (J_k (W^T A)_k - (W^T (A Jbar))_k),   A_p = 1 / D_p on valid pixels (0 elsewhere)

(W the window, W^T its adjoint, J the derivative images, Jbar = W J). Pixel noise of variance s_k^2, independent
between pixels and channels, gives the gradient the covariance ``sum_k s_k^2 a_k a_k^T``. Each ``s_k^2`` is read
off the residual the window cannot explain, ``e_k = (r_k - q_k) - (mu_r - mu_q)_k``: for independent noise of
variance s^2, ``E[e_k^2] = s^2 (1 - 2 w_kk + sum_j w_kj^2)``. Deterministic errors of the map, the lighting or an
occluder are residuals too and enter the same way, as if they were noise at those pixels: what moves a whole
image or region coherently (a gain, a gamma, a map's error) is not independent between pixels and is not in it.

It runs in numpy on the host (float32 images, the sum in float64) on the derivative pass's read-back images (the
twin by automatic differentiation: ``tests/reference/render_torch.py::cs_gradient_noise``).
"""

from __future__ import annotations

import numpy as np

from ..kernels.window import C2, RADIUS, window_weights

_TAPS = [float(t) for t in window_weights()]  # Python floats: the images keep their float32
#: E[e_k^2] / s^2 for independent noise away from the border (the 2-D window's centre weight and sum of squares)
NOISE_FACTOR = 1.0 - 2.0 * _TAPS[RADIUS] ** 2 + sum(t * t for t in _TAPS) ** 2


def _taps(pad: np.ndarray, n: int) -> np.ndarray:
    """``sum_j taps[j] pad[j:j + n]`` along axis 0, the symmetric taps paired."""
    out = _TAPS[RADIUS] * pad[RADIUS:RADIUS + n]
    pair = np.empty_like(out)  # one buffer for every pair: no temporaries per tap
    for j in range(RADIUS):
        np.add(pad[j:j + n], pad[2 * RADIUS - j:2 * RADIUS - j + n], out=pair)
        pair *= _TAPS[j]
        out += pair
    return out


def _filter_axis(x: np.ndarray, axis: int, adjoint: bool) -> np.ndarray:
    """The window's taps along ``axis`` of x, border coordinates clamped (replicate padding), or the adjoint:
    zero padding, the same symmetric taps, and the overhang folded back onto the border samples."""
    x = np.moveaxis(x, axis, 0)
    n = x.shape[0]
    if adjoint:
        zeros = np.zeros((2 * RADIUS,) + x.shape[1:], x.dtype)
        full = _taps(np.concatenate([zeros, x, zeros]), n + 2 * RADIUS)  # the padded signal's adjoint
        out = full[RADIUS:RADIUS + n]
        out[0] += full[:RADIUS].sum(0)
        out[-1] += full[RADIUS + n:].sum(0)
    else:
        out = _taps(np.concatenate([np.repeat(x[:1], RADIUS, 0), x, np.repeat(x[-1:], RADIUS, 0)]), n)
    return np.moveaxis(out, 0, axis)


def window(x: np.ndarray, adjoint: bool = False) -> np.ndarray:
    """The separable window (``kernels/window.py``: Gaussian taps, clamped border) over images x [H, W, ...] (any
    trailing channels), or its adjoint W^T."""
    return _filter_axis(_filter_axis(x, 1, adjoint), 0, adjoint)


def gradient_noise(rgb: np.ndarray, alpha: np.ndarray, drgb: np.ndarray, query_stats: np.ndarray,
                   mask_alpha: float) -> np.ndarray:
    """The cs gradient's covariance [6, 6] (float64) under independent pixel noise of the query.

    Args:
        rgb: [H, W, 3] the rendering at the pose; alpha: [H, W] its alpha (a pixel counts when >= ``mask_alpha``);
        drgb: [H, W, 3, 6] d rgb / d xi (``render_derivatives``); query_stats: [H, W, 3, >= 3] the query's window
        statistics (mu_q, s_qq, q per channel: a slot of ``upload_window_query``).
    """
    r = np.asarray(rgb, np.float32)
    J = np.asarray(drgb, np.float32)
    qs = np.asarray(query_stats, np.float32)
    mu_q, s_qq, q = qs[..., 0], qs[..., 1], qs[..., 2]
    valid = np.asarray(alpha) >= mask_alpha
    n = max(float(valid.sum()), 1.0)
    mu_r = window(r)
    s_rr = np.maximum(window(r * r) - mu_r * mu_r, 0.0)
    A = (valid[..., None] / (s_rr + s_qq + C2)).astype(np.float32)  # [H, W, 3]
    influence = (-2.0 / (3.0 * n)) * (J * window(A, adjoint=True)[..., None]
                                       - window(A[..., None] * window(J), adjoint=True))
    e = (r - q) - (mu_r - mu_q)
    weighted = influence * (e / np.float32(NOISE_FACTOR ** 0.5))[..., None]
    flat = weighted.reshape(-1, weighted.shape[-1]).astype(np.float64)
    return flat.T @ flat
