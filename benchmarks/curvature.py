"""Curvature: how well the polish's Gauss-Newton matrix models the cs cost's curvature at its minimum.

Usage: python -m benchmarks.curvature [--cases snow_sharp snow lego] [--step-px 0.2]
                                      [--out benchmarks/curvature.md]

Per query (priors 2 % of the depth / 1 deg off, seed 7, refined with the defaults; the returned pose), at the
polish's scoring sizes, three 6 x 6 matrices of the cs cost in the pose increment ``xi = (w, v)``:

- ``JtJ``: the derivative pass's Gauss-Newton matrix (``Renderer.pose_gradient``, what the polish solves with);
- the linearised Hessian: the exact Hessian, in float64 by PyTorch autograd (``tests/reference/render_torch``'s
  ``window_map``), of the cost of the rendering linearised in the pose, ``r + J xi`` (``Renderer.render_derivatives``):
  what ``JtJ`` would become with the rank-two terms of the windowed ratio that ``kernels/window_grad.py`` drops;
- the true Hessian: central differences of the pass's analytic gradient, ``--step-px`` of image motion per axis.

Printed per query and size: the eigenvalues of ``JtJ^-1 H`` for both (1 everywhere: ``JtJ`` is that curvature), and
``rho``, the spectral radius of ``I - JtJ^-1 H_true``: the factor by which an undamped Gauss-Newton step leaves the
error near the minimum (0: one step; > 1: it overshoots along some axis).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

import hgsloc_plugin as hp
from benchmarks.derivative_pass import renderer_for
from benchmarks.harness import (
    case_priors,
    load,
    write_keeping_notes,
)
from hgsloc_plugin.core.image import resize_image
from tests.reference.render_torch import window_map


def linearised_hessian(rgb: np.ndarray, drgb: np.ndarray, query: np.ndarray) -> np.ndarray:
    """[6, 6] Hessian at xi = 0 of ``1 - mean cs(rgb + drgb xi, query)`` (rgb, query [H, W, 3]; drgb [H, W, 3, 6]),
    float64 autograd."""
    r = torch.from_numpy(np.asarray(rgb, np.float64))
    J = torch.from_numpy(np.asarray(drgb, np.float64))
    q = torch.from_numpy(np.asarray(query, np.float64))
    cost = lambda xi: 1.0 - window_map(r + J @ xi, q).mean()  # noqa: E731
    return torch.autograd.functional.hessian(cost, torch.zeros(6, dtype=torch.float64)).numpy()


def curvature_row(renderer, cam: hp.Camera, image: np.ndarray, pose: hp.Pose, depth: float, bg, step_px: float
                  ) -> dict:
    """The three matrices at ``pose`` on ``cam``'s size, compared (see the module docstring)."""
    query = resize_image(image, cam.width, cam.height)
    qstats = renderer.upload_window_query(query)

    def gradient(T: hp.Pose):
        c, g, H = renderer.pose_gradient(cam, [T], qstats, bg)
        return np.asarray(g[0], np.float64), np.asarray(H[0], np.float64)

    _, jtj = gradient(pose)
    f = 0.5 * (cam.fx + cam.fy)
    per_px = np.array([1.0 / f] * 3 + [depth / f] * 3)  # xi per pixel of image motion, per axis
    fd = np.zeros((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = step_px * per_px[j]
        gp = gradient(pose.perturbed_in_camera(e[:3], e[3:]))[0]
        gm = gradient(pose.perturbed_in_camera(-e[:3], -e[3:]))[0]
        fd[:, j] = (gp - gm) / (2.0 * e[j])
    fd = 0.5 * (fd + fd.T)
    rgb, _, drgb = renderer.render_derivatives(cam, [pose], bg)
    lin = linearised_hessian(rgb[0], drgb[0], query)
    scale = np.outer(per_px, per_px)  # compare in pixel units: the axes' scales differ by orders of magnitude

    def ratios(h: np.ndarray) -> np.ndarray:
        return np.sort(np.linalg.eigvals(np.linalg.solve(jtj * scale, h * scale)).real)

    true = ratios(fd)
    return {"lin": ratios(lin), "true": true, "rho": float(np.max(np.abs(1.0 - true)))}


def run(case: str, step_px: float) -> list[str]:
    loaded = load(case)
    if loaded is None:
        print(f"skipping {case}: data not found", file=sys.stderr)
        return []
    cam, scene, qs, bg = loaded
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    rows = []
    for (name, _, image, _), prior in zip(qs, case_priors(case, qs, 2.0, 1.0)):
        result = refiner.refine(image, cam, prior)
        renderer, plan = renderer_for(scene, bg, hp.RasterConfig(), (cam, result.pose))
        for c in dict.fromkeys([plan.cam_coarse, plan.cam_final, plan.cam_polish]):
            m = curvature_row(renderer, c, image, result.pose, plan.depth, bg, step_px)
            fmt = lambda v: " ".join(f"{x:.2f}" for x in v)  # noqa: E731
            rows.append(f"| {case} | {name} | {c.width}x{c.height} | {fmt(m['lin'])} | {fmt(m['true'])} "
                        f"| {m['rho']:.2f} |")
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["snow_sharp", "snow", "lego"])
    ap.add_argument("--step-px", type=float, default=0.2)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    hp.init()
    lines = ["# Curvature at the minimum (`benchmarks/curvature.py`)", "",
             "Regenerate: `python -m benchmarks.curvature --out benchmarks/curvature.md`.", "",
             f"Returned poses of priors 2 % of the depth / 1 deg off (seed 7); true Hessian by central differences "
             f"of the analytic gradient at {args.step_px:g} px per axis. Columns: eigenvalues of `JtJ^-1 H`, "
             "ascending (all 1: the Gauss-Newton matrix is that curvature); rho: spectral radius of "
             "`I - JtJ^-1 H_true`, the error an undamped Gauss-Newton step leaves near the minimum.", "",
             "| case | query | size | linearised Hessian / JtJ | true Hessian / JtJ | rho |",
             "|---|---|---|---|---|---|"]
    for case in args.cases:
        lines += run(case, args.step_px)
    if args.out:
        write_keeping_notes(args.out, lines)


if __name__ == "__main__":
    main()
