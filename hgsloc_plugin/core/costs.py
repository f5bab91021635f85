"""Image-difference heuristics from the fused statistics of ``kernels/blend.py`` and ``kernels/window.py``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..kernels.layout import Stat


@dataclass(frozen=True)
class Metric:
    """A registered image cost (lower is better).

    Attributes:
        name: its name in ``RefineConfig.metric``, ``render_cost`` and the CLI.
        windowed: computed from windowed statistics of the rendered image (``kernels/window.py``,
            :func:`cost_from_window`); else from the blend's fused pixel statistics (:func:`cost_from_stats`).
        structural: its level is comparable across images, so the acceptance rule's alignment test applies.
        search: usable as the search's heuristic (``RefineConfig.metric``).
        polish: the polish's analytic pose derivatives are this cost's.
        summary: one line for help texts.
    """

    name: str
    windowed: bool
    structural: bool
    search: bool
    polish: bool
    summary: str


#: every cost, by name; a new cost is added here and in the kernel that gathers its statistics
METRICS: dict[str, Metric] = {m.name: m for m in (
    Metric("cs", True, True, True, True, "1 - mean SSIM contrast-structure over 11x11 Gaussian windows"),
    Metric("ssim", True, True, True, False, "1 - mean SSIM over 11x11 Gaussian windows"),
    Metric("sad", False, False, True, False, "sum of absolute differences over pixels and RGB (0-1 scale)"),
    Metric("ssd", False, False, False, False, "sum of squared differences over pixels and RGB (0-1 scale)"),
    Metric("psnr", False, False, True, False, "100 - PSNR of the valid pixels"),
    Metric("ncc", False, True, True, False, "1 - mean per-channel zero-mean normalised cross-correlation"),
    Metric("affine", False, False, True, False, "residual after a per-channel gain/offset fit, SAD-scaled"),
)}
FUSED_METRICS = tuple(k for k, m in METRICS.items() if not m.windowed)
WINDOW_METRICS = tuple(k for k, m in METRICS.items() if m.windowed)
SEARCH_METRICS = tuple(k for k, m in METRICS.items() if m.search)


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
