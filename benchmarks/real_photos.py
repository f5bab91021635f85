"""Real-photo benchmark: refine real photographs against imperfect 3DGS maps, every heuristic, one run.

Usage: python -m benchmarks.real_photos [--datasets snow lego] [--heuristics cs ssim sad affine] [--seeds 1]
                                        [--out benchmarks/real_photos.md]

Data (read in place, skipped with a message when absent):
- ``../shared/data/snow``: 6 held-out real phone photos with SfM poses against two 3DGS maps fitted to 85 other
  photos: ``snow`` (snow.ply, an imperfect map) and ``snow_sharp`` (snow_sharp.ply, a good one). Errors are in %
  of the query's median depth (about 4.5 units; 1 % = 2 cm-eq, 7-Scenes-equivalent cm at a 2 m depth) and degrees.
- ``../shared/data/lego``: a 3DGS fitted to Blender renders, 15 held-out renders (white background); errors in
  scene units and degrees.

Rows per heuristic (default config otherwise; ``cs`` is the default):
- ``truth``: started at the true pose. ``search`` is where the search ends (the drift of the cost minimum),
  ``returned`` what the refiner returns after its acceptance rule (``refine/trust.py``).
- ``a% / b deg``: camera-frame priors of exactly a % of depth (lego: 0.05 units) and b degrees, random directions.
- ``ACE-shaped`` / ``Marepo-shaped``: the camera-frame errors of the real ACE / Marepo estimates of 7-Scenes
  against the SfM pGT (``../shared/data/poses/7scenes``), one drawn per query, translation scaled by the query's
  depth over 2 m.
Each row: median and worst error of the prior and of the returned pose, queries ending worse than their prior
(in translation or rotation), accepted queries, renders and seconds per query.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import (
    DATA,
    load_dataset,
    localizer_errors,
    regenerate_line,
    shaped_prior,
    worse_count,
    write_keeping_notes,
)
from hgsloc_plugin.evaluation.noise import se3_noise


def protocols(dataset: str, queries, seeds: int):
    """name -> list of (query index, prior pose)."""
    out = {"truth": [(i, q[1]) for i, q in enumerate(queries)]}
    for pct, deg in ((1, 0.5), (2, 1.0), (5, 2.0)):
        label = f"{pct}% / {deg:g} deg" if dataset != "lego" else f"{0.05 * pct / 2:.3f} u / {deg:g} deg"
        rows = []
        for s in range(seeds):
            rng = np.random.default_rng(100 + s)
            for i, (_, gt, _, depth) in enumerate(queries):
                shift = pct / 100 * depth if dataset != "lego" else 0.05 * pct / 2
                rows.append((i, se3_noise(gt, deg, shift, rng)))
        out[label] = rows
    if (DATA / "poses" / "7scenes").exists():
        for method in ("ace", "marepo"):
            errs = localizer_errors(method)
            rows = []
            for s in range(seeds):
                rng = np.random.default_rng(200 + s)
                for i, (_, gt, _, depth) in enumerate(queries):
                    rows.append((i, shaped_prior(gt, errs[int(rng.integers(len(errs)))], depth)))
            out[f"{'ACE' if method == 'ace' else 'Marepo'}-shaped"] = rows
    else:
        print("skipping localizer-shaped priors: ../shared/data/poses/7scenes not found", file=sys.stderr)
    return out


def run(dataset: str, heuristics: list[str], seeds: int) -> list[str]:
    loaded = load_dataset(dataset)
    if loaded is None:
        return []
    cam, scene, queries, bg = loaded
    scale, unit = (lambda i: 100.0 / queries[i][3], "% depth") if dataset != "lego" else (lambda i: 1.0, "units")
    lines = [f"\n### {dataset}: {len(queries)} real {'photos' if dataset != 'lego' else 'renders'}, "
             f"{scene.num_gaussians} Gaussians; translation in {unit}, rotation in degrees\n",
             "| heuristic | start | prior median (worst) | search median | returned median (worst) | worse | "
             "accepted | renders | s / query |", "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    prots = protocols(dataset, queries, seeds)
    for h in heuristics:
        refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(metric=h, background=bg))
        for label, items in prots.items():
            e0, e1, es, acc, ren = [], [], [], 0, []
            t0 = time.perf_counter()
            for i, prior in items:
                name, gt, img, _ = queries[i]
                r = refiner.refine(img, cam, prior, name=name)
                for lst, p in ((e0, prior), (e1, r.pose), (es, r.search_pose)):
                    t, a = p.errors_to(gt)
                    lst.append((t * scale(i), a))
                acc += r.accepted
                ren.append(r.renders)
            sec = (time.perf_counter() - t0) / len(items)
            e0, e1, es = np.array(e0), np.array(e1), np.array(es)
            worse = worse_count(e0, e1)

            def fmt(e, worst=True):
                m = f"{np.median(e[:, 0]):.3f} / {np.median(e[:, 1]):.2f}"
                return m + (f" ({e[:, 0].max():.2f} / {e[:, 1].max():.2f})" if worst else "")

            row = (f"| {h}{' (default)' if h == hp.RefineConfig().metric else ''} | {label} | {fmt(e0)} | "
                   f"{fmt(es, False)} | {fmt(e1)} | {worse} / {len(items)} | {acc} / {len(items)} | "
                   f"{np.median(ren):.0f} | {sec:.1f} |")
            print(row, flush=True)
            lines.append(row)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", nargs="+", default=["snow", "snow_sharp", "lego"])
    ap.add_argument("--heuristics", nargs="+", default=["cs", "ssim", "sad", "affine"])
    ap.add_argument("--seeds", type=int, default=1, help="prior draws per query and protocol")
    ap.add_argument("--out", default=None, help="also write the tables as Markdown here")
    args = ap.parse_args()
    hp.init()
    lines = ["# Real-photo benchmark (`benchmarks/real_photos.py`)", "", regenerate_line(__file__),
             f"\nDefault config, scoring side {hp.RefineConfig().score_max_side} px; seeds {args.seeds}."]
    for ds in args.datasets:
        lines += run(ds, args.heuristics, args.seeds)
    if args.out:
        write_keeping_notes(Path(args.out), lines)


if __name__ == "__main__":
    main()
