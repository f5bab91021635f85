"""Sigma: the returned pose's sigma against the scatter of the poses over repeated photos of one view.

Usage: python -m benchmarks.sigma [--views 6] [--seeds 12] [--degradations noise photo] [--out benchmarks/sigma.md]

On the room (a perfect map: its queries are reference renders of it, so the truth is its minimum), each view is
photographed ``--seeds`` times: the same rendering, a new draw of the degradation each time (``noise``: pixel noise
alone, standard deviation 0.015; ``photo``: the trials' gain, gamma, blur, occluder and noise, ``trials.Views``),
each refined from its own prior 0.5 % of the depth / 0.3 deg off, with the map's floor set to nothing (1e-7 of
the depth, 1e-6 deg), so that sigma is the image's part alone (the pixel noise, ``refine/uncertainty.py``).
Per view and degradation: the accepted poses' camera-centre offsets from the truth (cm-eq: the depth scaled to
2 m) as their mean's length (the bias), their root-mean-square spread about it and about the truth (the error),
the median ``sigma_t`` and its ratio to that error (1 for a sigma that is the error's standard deviation, 3-D);
the same in degrees for the rotation. Nothing is tuned on it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.trials import PHOTO_DEGRADATION

DEGRADATIONS = {
    "noise": dict(gain=(1.0, 1.0), gamma=(1.0, 1.0), noise_std=0.015, blur_sigma=0.0, occluder=False),
    "photo": PHOTO_DEGRADATION,
}
NO_FLOOR = dict(map_floor_depth=1e-7, map_floor_deg=1e-6)


def view_rows(views: int, seeds: int, degradations: list[str]) -> list[str]:
    """Markdown rows: one per view and degradation, then the medians over the views per degradation."""
    import hgsloc_plugin as hp
    from benchmarks.trials import REFERENCE_DEPTH, SEED, Views
    from hgsloc_plugin.cli.demo.queries import degrade
    from hgsloc_plugin.evaluation.noise import apply_protocol

    hp.init()
    room = Views("room")
    refiner = hp.HGSLocPlugin(room.scene, hp.RefineConfig.preset("default", **NO_FLOOR))
    rows, summary = [], {d: [] for d in degradations}
    for k in range(views):
        gt, rgb, depth, _ = room.rendered(k)
        cm = 100.0 * REFERENCE_DEPTH / depth
        for name in degradations:
            offsets, rot, sig_t, sig_r = [], [], [], []
            for s in range(seeds):
                img = degrade(rgb, np.random.default_rng([SEED, k, s]), **DEGRADATIONS[name])
                prior = apply_protocol(gt, f"{0.5 * depth:.6f}cm,0.3deg", np.random.default_rng([SEED, k, s, 1]))
                r = refiner.refine(img, room.cam, prior)
                if r.accepted:
                    offsets.append(gt.offset_in_camera(r.pose)[3:] * cm)
                    rot.append(r.pose.errors_to(gt)[1])
                    sig_t.append(r.sigma_t * cm)
                    sig_r.append(r.sigma_r_deg)
            if not offsets:
                rows.append(f"| {k} | {name} | 0 / {seeds} | - | - | - | - | - | - | - | - |")
                continue
            c = np.array(offsets)
            bias = float(np.linalg.norm(c.mean(0)))
            spread = float(np.sqrt(((c - c.mean(0)) ** 2).sum(1).mean()))
            err = float(np.sqrt((c ** 2).sum(1).mean()))
            err_r = float(np.sqrt(np.mean(np.square(rot))))
            st, sr = float(np.median(sig_t)), float(np.median(sig_r))
            summary[name].append((st / err, sr / err_r))
            rows.append(f"| {k} | {name} | {len(c)} / {seeds} | {bias:.4f} | {spread:.4f} | {err:.4f} | {st:.4f} | "
                        f"{st / err:.1f} | {err_r:.4f} | {sr:.4f} | {sr / err_r:.1f} |")
    for name, ratios in summary.items():
        if ratios:
            t, r = np.median(np.array(ratios), axis=0)
            rows.append(f"| **median** | {name} | {len(ratios)} views | | | | | **{t:.1f}** | | | **{r:.1f}** |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--seeds", type=int, default=12, help="photos (degradation draws) per view")
    ap.add_argument("--degradations", nargs="+", default=list(DEGRADATIONS), choices=list(DEGRADATIONS))
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    t0 = time.time()
    head = ["| view | degradation | accepted | bias (cm-eq) | spread | error (rms) | sigma_t (median) | "
            "sigma_t / error | error R (rms, deg) | sigma_r (median) | sigma_r / error |", "|" + "---|" * 11]
    print("\n".join(head), flush=True)
    rows = view_rows(a.views, a.seeds, a.degradations)
    print("\n".join(rows))
    tail = f"\n{a.views} views x {a.seeds} photos, {time.time() - t0:.0f} s."
    print(tail)
    if a.out:
        from benchmarks.harness import regenerate_line, write_keeping_notes

        write_keeping_notes(Path(a.out), ["# Sigma against the scatter of repeated photos (`benchmarks/sigma.py`)", "",
                                          regenerate_line(__file__), "", *head, *rows, tail])


if __name__ == "__main__":
    main()
