"""Map floor: how far an imperfect map's cost minimum lies from the true pose, and what the refiner can see of it.

Usage: python -m benchmarks.map_floor [--datasets snow_sharp snow lego] [--draws 8] [--out benchmarks/map_floor.md]
       python -m benchmarks.map_floor --regional [--datasets snow_sharp snow lego]

Part 1, per real query (``../shared/data/snow``: real photos against the sharp map ``snow_sharp`` and the imperfect
``snow``; ``lego``: held-out renders): the map's minimum (the default refinement from 3 priors 2 % of depth / 1 deg
off, the median pose of those accepted), its error against the true (SfM) pose in 7-Scenes-equivalent cm (centre
error x 2 m / median depth) and degrees, the true pose's Mahalanobis distance under the refinement's covariance (6
degrees of freedom: median 2.3 when the covariance is right), the cs cost's rise from the minimum to the true pose,
and where other costs put the minimum on the line from the map's minimum (0) to the true pose (1), from a parabola
fitted to 9 renders on it: windowed cs with window sigma 1.5 (the kernels'), 3 or 6 px, each with both images
blurred by 0, 1 or 2 px, and pixel weightings fixed at the minimum (pixels the rendering explains, cs > 0.5 or 0.7;
opaque ones, alpha > 0.99; where the rendering is at least half as sharp as the photo). Per-pixel maps come from the
test suite's PyTorch reference (``tests/reference/render_torch.window_map``).

Part 2, the decision the acceptance rule would have to make: per query, ``--draws`` priors 0.25 cm-eq / 0.1 deg, as
many 1 cm-eq / 0.5 deg and as many 3 cm-eq / 1 deg off (random directions), each refined with the defaults. Per
prior, what the refiner can observe (the move from the prior to the search's pose in cm-eq and in Mahalanobis units
of the refined pose's covariance, and the acceptance rule's significance) and what it cannot (whether the search's
pose is > 1 cm-eq or > 0.5 deg further from the truth than the prior: "worse"). A rule that sees only the
observables returns the same verdict for the same observations; the last table gives, for the default acceptance
rule and for thresholds on the move (Mahalanobis, or in cm-eq: the refiner knows the depth), how many returned poses
would be worse and how many 1 / 2 cm recalls would be lost against accepting every search.
(A Mahalanobis move of nan: the search's pose has no covariance, i.e. the route ended without a polish.)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import hgsloc_plugin as hp
from benchmarks.harness import load_dataset, regenerate_line, write_keeping_notes
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.render import Renderer
from tests.reference.render_torch import window_map

LINE = np.linspace(-0.5, 1.5, 9)
#: part 2's priors: (cm-eq, deg) off the true pose in random directions
LEVELS = ((0.25, 0.1), (1.0, 0.5), (3.0, 1.0))
#: part 1's priors per query (2 % of depth / 1 deg off) whose median accepted result is taken as the minimum
MINIMUM_DRAWS = 3


def mahalanobis(xi: np.ndarray, cov: np.ndarray | None) -> float:
    if cov is None or not np.all(np.isfinite(cov)):
        return float("nan")
    return float(np.sqrt(xi @ np.linalg.solve(cov, xi)))


def blur(x: torch.Tensor, s: float) -> torch.Tensor:
    """[H, W, 3] float64 blurred by a Gaussian of ``s`` px (replicate padding)."""
    if s == 0:
        return x
    r = int(3 * s)
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=torch.float64) / s) ** 2)
    k = k / k.sum()
    K = (k[:, None] * k[None, :])[None, None].repeat(3, 1, 1, 1)
    return F.conv2d(F.pad(x.permute(2, 0, 1)[None], (r, r, r, r), mode="replicate"), K, groups=3)[0].permute(1, 2, 0)


def local_variance(x: torch.Tensor) -> torch.Tensor:
    """[H, W] channel mean of the 11 x 11 windowed variance of [H, W, 3]."""
    mu = blur(x, 1.5)
    return (blur(x * x, 1.5) - mu * mu).mean(-1)


def line_minima(renderer: Renderer, cam: hp.Camera, image: np.ndarray, pose: hp.Pose, xi: np.ndarray,
                bg) -> dict[str, float]:
    """Cost variant -> position of its minimum on pose -> pose.perturbed_in_camera(xi) (0 = pose, 1 = the end)."""
    poses = [pose.perturbed_in_camera(t * xi[:3], t * xi[3:]) for t in LINE]
    rgb, alpha, _ = renderer.render_full(cam, poses, bg)
    q = torch.from_numpy(image.astype(np.float64))
    rs = [torch.from_numpy(r.astype(np.float64)) for r in rgb]

    def argmin(cost):
        a = np.polyfit(LINE, cost, 2)
        return float(-a[1] / (2 * a[0])) if a[0] > 0 else float("nan")

    out = {}
    for sig, rad in ((1.5, 5), (3.0, 9), (6.0, 18)):
        for b in (0.0, 1.0, 2.0):
            out[f"cs w{sig:g} blur {b:g}"] = argmin([-window_map(blur(r, b), blur(q, b), False, sig, rad).mean().item()
                                                     for r in rs])
    j0 = int(np.argmin(np.abs(LINE)))
    maps = np.stack([window_map(r, q, False, 1.5, 5).numpy() for r in rs])
    sharp = (local_variance(rs[j0]).numpy() + 1e-4) / (local_variance(q).numpy() + 1e-4)
    weights = {"cs > 0.5": maps[j0] > 0.5, "cs > 0.7": maps[j0] > 0.7, "alpha > 0.99": alpha[j0] > 0.99,
               "sharp > 0.5": sharp > 0.5}
    for k, w in weights.items():
        w = w.astype(np.float64)
        out[k] = argmin(-(maps * w).sum((1, 2)) / max(w.sum(), 1.0))
    return out


def cm_eq(t: float, depth: float) -> float:
    return t * 200.0 / depth


def floor_part(name: str, refiner: hp.HGSLocPlugin, cam, queries, bg) -> list[str]:
    renderer = refiner.renderer
    lines = [f"\n### {name}: the map's minimum per query ({refiner.renderer.n} Gaussians)\n",
             "| query | minimum: error cm-eq / deg | true pose: Mahalanobis | cs rise min -> truth | "
             "minimum on the line min (0) -> truth (1), per cost |", "|---|---|---|---|---|"]
    for i, (_name, gt, img, depth) in enumerate(queries):
        rng = np.random.default_rng(500 + i)
        found = []
        for _ in range(MINIMUM_DRAWS):
            r = refiner.refine(img, cam, se3_noise(gt, 1.0, 0.02 * depth, rng))
            if r.accepted:
                found.append(r)
        if not found:
            lines.append(f"| {i} | no accepted refinement | | | |")
            continue
        errs = np.array([cm_eq(r.pose.errors_to(gt)[0], depth) for r in found])
        best = found[int(np.argsort(errs)[len(errs) // 2])]
        xi = best.pose.offset_in_camera(gt)
        c = renderer.window_cost(cam, [best.pose, gt], Renderer.upload_window_query(img), bg)
        cs = 1.0 - c[:, 0] / c[:, 1]
        lm = line_minima(renderer, cam, img, best.pose, xi, bg)
        t, a = best.pose.errors_to(gt)
        lines.append(f"| {i} | {cm_eq(t, depth):.2f} / {a:.2f} | {mahalanobis(xi, best.covariance):.1f} | "
                     f"{100 * (cs[1] / cs[0] - 1):+.1f} % | " + ", ".join(f"{k} {v:+.2f}" for k, v in lm.items())
                     + " |")
        print(lines[-1], flush=True)
    return lines


def decision_part(name: str, refiner: hp.HGSLocPlugin, cam, queries, draws: int) -> list[str]:
    rows = []
    for i, (_name, gt, img, depth) in enumerate(queries):
        for level, (cm, deg) in enumerate(LEVELS):
            rng = np.random.default_rng(700 + 10 * i + level)
            for _ in range(draws):
                prior = se3_noise(gt, deg, cm / 200.0 * depth, rng)
                r = refiner.refine(img, cam, prior)
                if r.search_pose is None or r.assessment is None:
                    continue
                t0, a0 = prior.errors_to(gt)
                t1, a1 = r.search_pose.errors_to(gt)
                move = cm_eq(prior.errors_to(r.search_pose)[0], depth)
                rows.append(dict(q=i, level=f"{cm:g} cm / {deg:g} deg", e0=(cm_eq(t0, depth), a0),
                                 e1=(cm_eq(t1, depth), a1), move=move,
                                 maha=mahalanobis(r.search_pose.offset_in_camera(prior), r.covariance),
                                 sig=r.assessment.significance, accepted=r.accepted))
    worse = lambda d: d["e1"][0] > d["e0"][0] + 1.0 or d["e1"][1] > d["e0"][1] + 0.5  # noqa: E731
    lines = [f"\n### {name}: what the refiner sees vs whether its pose is worse ({len(rows)} searches)\n",
             "| query | prior | searches | worse | move cm-eq (min-max) of worse / of the others | "
             "Mahalanobis move of worse / of the others | significance of worse / of the others |",
             "|---|---|---|---|---|---|---|"]

    def span(vals):
        return f"{min(vals):.1f}-{max(vals):.1f}" if vals else "-"

    for i in range(len(queries)):
        for level in sorted({d["level"] for d in rows}):
            sel = [d for d in rows if d["q"] == i and d["level"] == level]
            w = [d for d in sel if worse(d)]
            o = [d for d in sel if not worse(d)]
            lines.append(f"| {i} | {level} | {len(sel)} | {len(w)} | {span([d['move'] for d in w])} / "
                         f"{span([d['move'] for d in o])} | {span([d['maha'] for d in w])} / "
                         f"{span([d['maha'] for d in o])} | {span([d['sig'] for d in w])} / "
                         f"{span([d['sig'] for d in o])} |")
    lines += ["", "Rules that keep the prior on what the refiner observes (searches of every query and "
              "level above; recall counted on the returned pose vs accepting every search):", "",
              "| keep the prior when | worse | recall at 1 cm / 1 deg lost | at 2 cm / 2 deg lost |",
              "|---|---|---|---|"]

    def recall(rs, key, cm):
        return sum(1 for d in rs if d[key][0] <= cm and d[key][1] <= cm)

    def rule_row(label, keep):
        out = [dict(d, out=d["e0"] if keep(d) else d["e1"]) for d in rows]
        nw = sum(1 for d in out if not keep(d) and worse(d))
        return (f"| {label} | {nw} | {recall(rows, 'e1', 1.0) - recall(out, 'out', 1.0)} | "
                f"{recall(rows, 'e1', 2.0) - recall(out, 'out', 2.0)} |")

    lines.append(rule_row("the default acceptance rule", lambda d: not d["accepted"]))
    for th in (1.0, 2.0, 4.0, 8.0, 16.0):
        lines.append(rule_row(f"Mahalanobis move < {th:g}", lambda d, th=th: not d["maha"] >= th))
    for th in (1.0, 2.0, 3.0, 4.0):
        lines.append(rule_row(f"move < {th:g} cm-eq", lambda d, th=th: d["move"] < th))
    print("\n".join(lines), flush=True)
    return lines


#: ``--regional``: the image halves a query's minimum is found on (column / row ranges as fractions of the image)
HALVES = {"left": (0.0, 0.5, 0.0, 1.0), "right": (0.5, 1.0, 0.0, 1.0), "top": (0.0, 1.0, 0.0, 0.5),
          "bottom": (0.0, 1.0, 0.5, 1.0)}


def regional_part(name: str, refiner: hp.HGSLocPlugin, cam, queries) -> list[str]:
    """``--regional``: per query, the minimum the refinement reaches from the true pose (``search_pose``) on the whole
    image and on each half of it (a crop with its own principal point), as the offset of its centre in the true
    camera's x / y / z (% of the depth) and its rotation (deg); then how well the floor of the nearest other views
    (k = 1, 2, 3; distance: the angle between the optical axes in radians plus the centres' distance over the
    depth) and of all other views (the root mean square, as ``MapFloor.without``) predict each view's own offset
    (its offset over that floor)."""
    lines = [f"\n### {name}: the minimum on image halves, and the floor of nearby views\n",
             "| query | image | centre offset x / y / z (% of depth) | rotation (deg) |", "|---|---|---|---|"]
    offsets = []
    for i, (qname, gt, img, depth) in enumerate(queries):
        h, w = img.shape[:2]
        for part, (x0, x1, y0, y1) in {"whole": (0.0, 1.0, 0.0, 1.0), **HALVES}.items():
            c0, c1, r0, r1 = round(x0 * w), round(x1 * w), round(y0 * h), round(y1 * h)
            crop = hp.Camera(c1 - c0, r1 - r0, cam.fx, cam.fy, cam.cx - c0, cam.cy - r0)
            r = refiner.refine(np.ascontiguousarray(img[r0:r1, c0:c1]), crop, gt, name=f"{qname} {part}")
            if r.search_pose is None:
                lines.append(f"| {i} | {part} | no refined pose ({r.rejected}) | |")
                continue
            d = 100.0 * gt.R @ (r.search_pose.centre() - gt.centre()) / depth
            if part == "whole":
                offsets.append(float(np.linalg.norm(d)))
            lines.append(f"| {i} | {part} | {d[0]:+.2f} / {d[1]:+.2f} / {d[2]:+.2f} | "
                         f"{r.search_pose.errors_to(gt)[1]:.2f} |")
    off = np.array(offsets)
    if len(off) == len(queries) > 1:
        centres = np.array([gt.centre() for _, gt, _, _ in queries])
        axes = np.array([gt.R[2] for _, gt, _, _ in queries])
        depths = np.array([d for *_, d in queries])
        lines += ["", "| floor from | each view's offset over it (query 0, 1, ...) |", "|---|---|"]
        for k in (1, 2, 3):
            ratio = []
            for i in range(len(off)):
                dist = (np.arccos(np.clip(axes @ axes[i], -1.0, 1.0))
                        + np.linalg.norm(centres - centres[i], axis=1) / depths[i])
                dist[i] = np.inf
                ratio.append(off[i] / np.sqrt(np.mean(off[np.argsort(dist)[:k]] ** 2)))
            lines.append(f"| the {k} nearest other view{'s' if k > 1 else ''} | "
                         + ", ".join(f"{v:.2f}" for v in ratio) + " |")
        rest = [off[i] / np.sqrt(np.mean(np.delete(off, i) ** 2)) for i in range(len(off))]
        lines.append("| all other views | " + ", ".join(f"{v:.2f}" for v in rest) + " |")
    print("\n".join(lines), flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["snow_sharp", "snow", "lego"])
    ap.add_argument("--queries", type=int, default=6)
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--out", default=None)
    ap.add_argument("--regional", action="store_true",
                    help="only the minimum on each image half and the floor of nearby views, per dataset")
    args = ap.parse_args()
    hp.init()
    t0 = time.perf_counter()
    lines = ["# Map floor (`benchmarks/map_floor.py`)", "", regenerate_line(__file__), "",
             f"One run on this machine ({hp.current_arch()}), {args.draws} priors per query and level."]
    for name in args.datasets:
        loaded = load_dataset(name)
        if loaded is None:
            continue
        cam, scene, queries, bg = loaded
        queries = queries[:args.queries]
        refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
        if args.regional:
            regional_part(name, refiner, cam, queries)
            continue
        lines += floor_part(name, refiner, cam, queries, bg)
        lines += decision_part(name, refiner, cam, queries, args.draws)
    if args.regional:
        return
    lines.append(f"\nTotal {time.perf_counter() - t0:.0f} s.")
    if args.out:
        write_keeping_notes(Path(args.out), lines)
    else:
        print("\n".join(lines))


if __name__ == "__main__":
    main()
