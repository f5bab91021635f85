"""Image-difference heuristics from the fused statistics of ``kernels/blend.py`` and ``kernels/window.py``."""

from __future__ import annotations

import numpy as np

from .kernels.layout import Stat

FUSED_METRICS = ("sad", "ssd", "psnr", "ncc", "affine")
WINDOW_METRICS = ("cs", "ssim")


def cost_from_window(sums: np.ndarray) -> np.ndarray:
    """Per-pose cost ``1 - mean`` of the windowed similarity (``kernels/window.py``), from [B, 2] (sum, pixels).

    0 for identical local structure; a pose with no valid pixel costs 1 (as an unrelated image would).
    """
    sums = np.asarray(sums, dtype=np.float64)
    return 1.0 - sums[:, 0] / np.maximum(sums[:, 1], 1.0)


def cost_from_stats(stats: np.ndarray, metric: str, num_pixels: int) -> np.ndarray:
    """Per-pose cost from statistics [B, Stat.SIZE] (float64).

    Args:
        stats: the ``kernels.layout.Stat`` record per pose (n_valid, SAD, SSD, per-channel sums).
        metric: "sad" raw sum |r - q| over valid pixels and RGB (the paper's L1);
            "ssd" sum of squares; "psnr" 100 - PSNR of the valid pixels;
            "ncc" 1 - mean over channels of the zero-mean normalised cross-correlation (gain/offset invariant);
            "affine" mean absolute residual after a per-channel least-squares gain/offset fit of the
            rendering to the query, scaled to a SAD-like sum over the image (exposure robust).
        num_pixels: pixels in the image (to express masked costs on the full-image scale).

    Returns:
        float64 [B]; lower is better.
    """
    stats = np.asarray(stats, dtype=np.float64)
    n = np.maximum(stats[:, Stat.N], 1.0)
    if metric == "sad":
        return stats[:, Stat.SAD].copy()
    if metric == "ssd":
        return stats[:, Stat.SSD].copy()
    if metric == "psnr":
        mse = np.maximum(stats[:, Stat.SSD] / (3.0 * n), 1e-12)
        return 100.0 - 10.0 * np.log10(1.0 / mse)
    ch = stats[:, Stat.CHANNELS:Stat.SIZE].reshape(-1, 3, Stat.PER_CHANNEL)
    sr, sq, srr, sqq, srq = (ch[..., k] for k in (Stat.SR, Stat.SQ, Stat.SRR, Stat.SQQ, Stat.SRQ))
    nn = n[:, None]
    var_r = np.maximum(srr - sr * sr / nn, 0.0)
    var_q = np.maximum(sqq - sq * sq / nn, 0.0)
    cov = srq - sr * sq / nn
    if metric == "ncc":
        ncc = cov / np.sqrt(np.maximum(var_r * var_q, 1e-20))
        return 1.0 - ncc.mean(axis=1)
    if metric == "affine":
        # residual of q ~ a r + c: var_q - cov^2 / var_r  (sum of squared residuals per channel)
        res = np.maximum(var_q - cov * cov / np.maximum(var_r, 1e-12), 0.0)
        rmse = np.sqrt(res.sum(axis=1) / (3.0 * n))
        return rmse * 3.0 * num_pixels
    raise ValueError(f"unknown metric {metric!r}; choose from {FUSED_METRICS} or {WINDOW_METRICS}")
