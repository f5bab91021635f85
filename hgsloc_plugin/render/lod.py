"""Level of detail for the coarse pyramid levels: Gaussians far below a pixel merged per cell.

:func:`coarse_lod` builds, once per query, a renderer for the coarse camera over the query's trust region in
which every Gaussian whose standard deviation is at most ``tau_px`` pixels (at the closest depth any pose of the
region gets) is put in a cubic cell of side at most ``tau_px`` pixels (power-of-two sides), and the Gaussians of
one cell are replaced by one: weights ``w = o * a`` (opacity times the dilated footprint ``a`` in pixels^2),
weighted mean, moment-matched covariance, weighted SH coefficients, and the opacity
``1 - prod(1 - o_i min(1, a_i / a))``; every other Gaussian, and every one-member cell, is kept as it is. Merged
Gaussians sit in the resident order at their first member's place. The result is approximate (opt-in:
``Tuning.coarse_lod_pixels``; measurements in ``benchmarks/defaults.md``).
"""

from __future__ import annotations

import math

import numpy as np

from ..core.camera import Camera
from ..core.pose import Pose
from . import Renderer

DILATION_PX2 = 0.3  # RasterConfig.eps2d's default; the footprint proxy only needs its order of magnitude


def merge_groups(arrays: dict[str, np.ndarray], members: np.ndarray, g: np.ndarray, M: int, unit: np.ndarray,
                 eps2d: float = DILATION_PX2) -> tuple[np.ndarray, ...]:
    """Moment-match groups of Gaussians into one Gaussian each (the rule of the module docstring).

    Args:
        arrays: ``Renderer.arrays()`` [n]; members [m]: the indices merged; g [m]: each member's group, in
            ``range(M)``, every group with a member; unit [m]: scene units per pixel where each member is used
            (it sets the member's footprint in pixels^2, hence its weight).

    Returns:
        float64 arrays of the M merged Gaussians: means [M, 3], cov3d [M, 6], opacities [M], sh [M, K, 3] and
        smax [M] (the square root of the covariance's trace, >= the largest standard deviation).
    """
    means = arrays["means"].astype(np.float64)
    cov = arrays["cov3d"].astype(np.float64)
    opac = arrays["opacities"].astype(np.float64)
    tr = cov[members][:, [0, 3, 5]].sum(axis=1)
    a_i = tr / 3.0 / unit ** 2 + eps2d  # dilated footprint in pixels^2 (isotropic proxy)
    o_i = opac[members]
    w = o_i * a_i
    W = np.bincount(g, w, M)

    def wsum(x):
        return np.bincount(g, w * x, M) / W

    mu = np.stack([wsum(means[members, k]) for k in range(3)], 1)
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    cov_m = np.stack([wsum(cov[members, c] + means[members, i] * means[members, j]) - mu[:, i] * mu[:, j]
                      for c, (i, j) in enumerate(pairs)], 1)
    sh = arrays["sh"]
    sh_m = np.stack([np.stack([wsum(sh[members, k, c].astype(np.float64)) for c in range(sh.shape[2])], 1)
                     for k in range(sh.shape[1])], 1)
    unit_m = np.bincount(g, w * unit, M) / W
    tr_m = np.maximum(cov_m[:, [0, 3, 5]].sum(axis=1), 0.0)
    a_m = tr_m / 3.0 / unit_m ** 2 + eps2d
    cover = np.minimum(o_i * np.minimum(1.0, a_i / a_m[g]), 0.999)
    o_m = 1.0 - np.exp(np.bincount(g, np.log1p(-cover), M))
    smax_m = np.sqrt(tr_m)  # >= the largest std. dev.
    return mu, cov_m, o_m, sh_m, smax_m


def merge_cells(arrays: dict[str, np.ndarray], depth: np.ndarray, f: float, tau_px: float,
                eps2d: float = DILATION_PX2) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Merge sub-``tau_px`` Gaussians per cell (see the module docstring).

    Args:
        arrays: ``Renderer.arrays()`` of the candidates [n]; depth [n]: the closest camera depth of each centre
            (scene units, > 0); f: focal length in pixels; tau_px: cell side and member size bound in pixels.

    Returns:
        (the merged arrays [m], in the input's order of first members; source [m]: the input index of each
        output Gaussian, -1 for a merged one).
    """
    means = arrays["means"].astype(np.float64)
    n = len(means)
    unit = depth / f  # scene units per pixel
    small = arrays["smax"].astype(np.float64) <= tau_px * unit
    idx_small = np.flatnonzero(small)
    level = np.floor(np.log2(tau_px * unit[idx_small])).astype(np.int64)
    side = np.exp2(level.astype(np.float64))
    cell = np.floor(means[idx_small] / side[:, None]).astype(np.int64)
    order = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0], level))
    keys = np.column_stack([level, cell])[order]
    new = np.ones(len(order), bool)
    new[1:] = np.any(keys[1:] != keys[:-1], axis=1)
    gid_sorted = np.cumsum(new) - 1
    group = np.empty(len(order), np.int64)
    group[order] = gid_sorted  # group of each small Gaussian
    G = int(gid_sorted[-1]) + 1 if len(order) else 0
    size = np.bincount(group, minlength=G)
    merged_member = size[group] > 1
    # Gaussians kept as they are: not small, or alone in their cell
    keep = np.ones(n, bool)
    keep[idx_small[merged_member]] = False
    members = idx_small[merged_member]
    g = group[merged_member]
    _, g = np.unique(g, return_inverse=True)  # dense ids of the merged cells
    M = int(g.max()) + 1 if g.size else 0
    mu, cov_m, o_m, sh_m, smax_m = merge_groups(arrays, members, g, M, unit[members], eps2d)
    first = np.full(M, n, np.int64)
    np.minimum.at(first, g, members)
    kept = np.flatnonzero(keep)
    place = np.concatenate([kept, first])
    out_order = np.argsort(place, kind="stable")
    out = {
        "means": np.concatenate([arrays["means"][kept], mu.astype(np.float32)])[out_order],
        "cov3d": np.concatenate([arrays["cov3d"][kept], cov_m.astype(np.float32)])[out_order],
        "opacities": np.concatenate([arrays["opacities"][kept], o_m.astype(np.float32)])[out_order],
        "sh": np.concatenate([arrays["sh"][kept], sh_m.astype(np.float32)])[out_order],
        "smax": np.concatenate([arrays["smax"][kept], smax_m.astype(np.float32)])[out_order],
    }
    source = np.concatenate([kept, np.full(M, -1, np.int64)])[out_order]
    return out, source


def coarse_lod(renderer: Renderer, camera: Camera, pose: Pose, max_shift: float, max_rotation_deg: float,
               tau_px: float = 0.5) -> Renderer:
    """A renderer for ``camera`` and every pose within ``max_shift`` / ``max_rotation_deg`` of ``pose``: the Gaussians
    such poses can see (``Renderer.working_set``), sub-``tau_px`` ones merged per cell (:func:`merge_cells`).
    Approximate: for the coarse levels only."""
    if not tau_px > 0:
        raise ValueError(f"tau_px must be > 0, got {tau_px}")
    ws = renderer.working_set([camera], pose, max_shift, max_rotation_deg)
    arrays = ws.arrays()
    z = arrays["means"].astype(np.float64) @ pose.R[2] + pose.tvec[2]
    near = max(renderer.config.near_plane, 1e-6)
    depth = np.maximum(z - max_shift, near)  # the closest any pose of the region gets
    f = max(camera.fx, camera.fy)
    merged, source = merge_cells(arrays, depth, f, tau_px, renderer.config.eps2d)
    src = np.where(source >= 0, ws.source_index[np.maximum(source, 0)], -1)
    return ws.derived(merged, src)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)
