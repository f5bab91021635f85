"""Figures (PNG, written atomically): the diagonal-split comparison with heat maps, error and cost plots."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..core.camera import Camera
from ..core.fileio import atomic_write_bytes
from ..core.pose import Pose
from ..core.scene import GaussianScene
from ..render import render


def diagonal_split(rendering: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Rendering above the anti-diagonal, query below it, with a thin white seam: [H, W, 3] float."""
    h, w = query.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w]
    d = xx / max(w - 1, 1) + yy / max(h - 1, 1) - 1.0
    out = np.where((d < 0)[..., None], rendering, query)
    seam = np.abs(d) < 1.5 / max(h, w)
    out[seam] = 1.0
    return np.clip(out, 0, 1)


def save_png(img: np.ndarray, path) -> Path:
    """Write an image [H, W, 3] float in [0, 1] as an 8-bit PNG (atomically, with the umask's mode)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray((np.clip(img, 0, 1) * 255).round().astype(np.uint8)).save(buf, format="PNG")
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


#: the heat map's colour scale: mean |rendering - query| over RGB, 0 (black) to this (yellow)
HEAT_MAX = 0.5


def comparison_figure(scene: GaussianScene, camera: Camera, query: np.ndarray, coarse: Pose, refined: Pose,
                      path, background=(0.0, 0.0, 0.0), max_side: int = 320) -> Path:
    """One PNG of four titled panels: the coarse and the refined pose's rendering split with the query along the
    diagonal (rendering top left, query bottom right: misalignment shows at the seam), and each one's heat map of
    the mean absolute difference to the query over RGB (0 to ``HEAT_MAX``, with a colour bar)."""
    fig = comparison_panels(scene, camera, query, coarse, refined, background, max_side)
    return _save_figure(_pyplot(), fig, path, tight=False)


def comparison_panels(scene: GaussianScene, camera: Camera, query: np.ndarray, coarse: Pose, refined: Pose,
                      background=(0.0, 0.0, 0.0), max_side: int = 320):
    """The matplotlib figure of :func:`comparison_figure` (not saved, not closed)."""
    from ..core.image import resize_image

    cam = camera.with_max_side(max_side)
    q = resize_image(query.astype(np.float32), cam.width, cam.height)
    r0, r1 = render(scene, cam, [coarse, refined], background=background)
    plt = _pyplot()
    pw, ph = _panel_size(cam)
    fig, ax = plt.subplots(2, 2, figsize=(2 * pw + 1.2, 2 * ph + 1.3))
    for col, (r, what) in enumerate(((r0, "coarse"), (r1, "refined"))):
        ax[0, col].imshow(diagonal_split(r, q))
        ax[0, col].set_title(f"{what} pose:\nrendering (top left) | query", fontsize=8)
        d = np.abs(r.astype(np.float64) - q).mean(-1)
        im = ax[1, col].imshow(d, cmap="inferno", vmin=0.0, vmax=HEAT_MAX)
        ax[1, col].set_title(f"{what}: |rendering - query|\nmean {d.mean():.3f}", fontsize=8)
    for a in ax.ravel():
        a.set_axis_off()
    fig.colorbar(im, ax=ax[1, :].tolist(), shrink=0.8, label="mean |difference| over RGB")
    return fig


def _panel_size(cam: Camera, min_width: float = 2.6) -> tuple[float, float]:
    """(width, height) in inches of an image panel: 80 px an inch, at least ``min_width`` wide (room for a title
    over a portrait image)."""
    w = max(cam.width / 80, min_width)
    return w, w * cam.height / cam.width


def check_figure(query: np.ndarray, rendering: np.ndarray, name: str, cost: float, path) -> Path:
    """One PNG of two titled panels: the query photo and the map's rendering at its pose as given (``hgsloc
    check``), with the pose's cs cost."""
    plt = _pyplot()
    h, w = query.shape[:2]
    pw, ph = _panel_size(Camera.from_focal(w, h, 1.0))
    fig, ax = plt.subplots(1, 2, figsize=(2 * pw + 0.4, ph + 0.9))
    ax[0].imshow(np.clip(query, 0, 1))
    ax[0].set_title(f"photo\n{name}", fontsize=8)
    ax[1].imshow(np.clip(rendering, 0, 1))
    ax[1].set_title(f"map at the pose as given\ncs cost {cost:.3f}", fontsize=8)
    for a in ax:
        a.set_axis_off()
    return _save_figure(plt, fig, path)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(plt, fig, path, tight: bool = True) -> Path:
    if tight:
        fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def plot_errors(before_t, after_t, before_r, after_r, path, unit: str = "cm") -> Path:
    """Scatter of per-query error before vs after (translation in ``unit``, rotation deg) and cumulative curves."""
    plt = _pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(13, 4))
    for k, (a, b, lab) in enumerate(((before_t, after_t, f"translation error ({unit})"),
                                     (before_r, after_r, "rotation error (deg)"))):
        ax[k].scatter(a, b, s=12)
        m = max(np.max(a), np.max(b), 1e-6)
        ax[k].plot([0, m], [0, m], "k--", lw=0.8, label="unchanged")
        ax[k].set_xlabel("coarse " + lab)
        ax[k].set_ylabel("refined " + lab)
        ax[k].set_title(f"{lab.split(' (')[0]} per query (below the line: better)", fontsize=9)
        ax[k].legend(fontsize=8)
    for v, lab in ((before_t, "coarse"), (after_t, "refined")):
        srt = np.sort(v)
        ax[2].plot(srt, np.arange(1, len(srt) + 1) / len(srt), label=lab)
    ax[2].set_xlabel(f"translation error ({unit})")
    ax[2].set_ylabel("fraction of queries")
    ax[2].set_title("cumulative translation error", fontsize=9)
    ax[2].legend()
    return _save_figure(plt, fig, path)


def cost_trace(entry: dict) -> list[tuple[str, float, float]]:
    """The cost along one query's refinement, from its report entry: (stage, cost before, cost after) for each
    search level (its start is the previous level's end) and each polish stage, labelled by scoring size;
    [] when nothing ran."""
    out, prev = [], entry.get("cost_initial")
    for i, lv in enumerate(entry.get("levels") or []):
        out.append((f"level {i + 1}\n{lv['width']}x{lv['height']}", prev, lv["best_cost"]))
        prev = lv["best_cost"]
    for st in entry.get("polish") or []:
        out.append((f"polish\n{st['width']}x{st['height']}", st["cost_start"], st["cost"]))
    return [(k, a if a is not None else b, b) for k, a, b in out if b is not None]


def plot_costs(entries: list[dict], path, names: list[str] | None = None) -> Path | None:
    """The cost (lower is better) before and after each stage of each query's refinement (:func:`cost_trace`),
    one colour per query, named in the legend (``names``, in the order of ``entries``; the first 10); nothing is
    written (None) when no query has a stage."""
    fig = cost_figure(entries, names)
    return None if fig is None else _save_figure(_pyplot(), fig, path)


def cost_figure(entries: list[dict], names: list[str] | None = None):
    """The matplotlib figure of :func:`plot_costs` (None when no query has a stage)."""
    names = list(names) if names is not None else [f"query {k + 1}" for k in range(len(entries))]
    traces = [(n, t) for n, t in zip(names, (cost_trace(e) for e in entries)) if t]
    if not traces:
        return None
    plt = _pyplot()
    stages = list(dict.fromkeys(k for _, t in traces for k, _, _ in t))
    fig, ax = plt.subplots(figsize=(1.6 * len(stages) + 4.5, 4))
    for q, (name, t) in enumerate(traces):
        colour = f"C{q % 10}"
        for i, (k, before, after) in enumerate(t):
            x = stages.index(k)
            ax.plot([x - 0.3, x + 0.3], [before, after], color=colour, marker=".", lw=1.0,
                    label=name if i == 0 and q < 10 else None)
    ax.set_xticks(range(len(stages)), stages, fontsize=8)
    ax.set_ylabel("cost (lower is better)")
    ax.set_title("cost before -> after each stage (each segment: one stage of one query)", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0),
              title=None if len(traces) <= 10 else f"first 10 of {len(traces)}")
    fig.tight_layout()
    return fig
