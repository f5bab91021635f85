"""Figures: the paper's diagonal-split comparison, difference heat maps, and error / cost plots (PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .camera import Camera
from .pose import Pose
from .render import render
from .scene import GaussianScene


def diagonal_split(rendering: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Rendering above the anti-diagonal, query below it, with a thin white seam: [H, W, 3] float."""
    h, w = query.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    d = xx / max(w - 1, 1) + yy / max(h - 1, 1) - 1.0
    out = np.where((d < 0)[..., None], rendering, query)
    seam = np.abs(d) < 1.5 / max(h, w)
    out[seam] = 1.0
    return np.clip(out, 0, 1)


def heat_map(rendering: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Absolute difference averaged over RGB, as an RGB heat map [H, W, 3] (matplotlib 'inferno')."""
    from matplotlib import colormaps

    d = np.abs(rendering.astype(np.float64) - query).mean(-1)
    return colormaps["inferno"](np.clip(d / 0.5, 0, 1))[..., :3]


def save_png(img: np.ndarray, path) -> Path:
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(path)
    return path


def comparison_figure(scene: GaussianScene, camera: Camera, query: np.ndarray, coarse: Pose, refined: Pose,
                      path, background=(0.0, 0.0, 0.0), max_side: int = 320) -> Path:
    """One PNG: [coarse split | refined split] over [coarse heat map | refined heat map].

    Rendering and query are split along the diagonal, so misalignment shows at the seam.
    """
    from .image import resize_image

    cam = camera.with_max_side(max_side)
    q = resize_image(query.astype(np.float32), cam.width, cam.height)
    r0, r1 = render(scene, cam, [coarse, refined], background=background)
    top = np.concatenate([diagonal_split(r0, q), np.ones((cam.height, 4, 3)), diagonal_split(r1, q)], 1)
    bot = np.concatenate([heat_map(r0, q), np.ones((cam.height, 4, 3)), heat_map(r1, q)], 1)
    return save_png(np.concatenate([top, np.ones((4, top.shape[1], 3)), bot], 0), path)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(plt, fig, path) -> Path:
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_errors(before_t, after_t, before_r, after_r, path) -> Path:
    """Scatter of per-query error before vs after (translation cm, rotation deg) and cumulative curves."""
    plt = _pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(13, 4))
    for a, b, lab in ((before_t, after_t, "translation error (cm)"), (before_r, after_r, "rotation error (deg)")):
        k = 0 if "cm" in lab else 1
        ax[k].scatter(a, b, s=12)
        m = max(np.max(a), np.max(b), 1e-6)
        ax[k].plot([0, m], [0, m], "k--", lw=0.8)
        ax[k].set_xlabel("coarse " + lab)
        ax[k].set_ylabel("refined " + lab)
    for v, lab in ((before_t, "coarse"), (after_t, "refined")):
        s = np.sort(v)
        ax[2].plot(s, np.arange(1, len(s) + 1) / len(s), label=lab)
    ax[2].set_xlabel("translation error (cm)")
    ax[2].set_ylabel("fraction of queries")
    ax[2].legend()
    return _save_figure(plt, fig, path)


def plot_costs(histories: list[list[float]], path) -> Path:
    """Best cost after each expansion, one line per query (normalised by its first value)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for h in histories:
        if h:
            ax.plot(np.asarray(h) / max(h[0], 1e-12), lw=0.8)
    ax.set_xlabel("expansion")
    ax.set_ylabel("best cost / first cost")
    return _save_figure(plt, fig, path)
