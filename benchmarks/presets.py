"""Presets: each ``RefineConfig`` preset's time per query and accuracy against the default's, in one run.

Usage: python -m benchmarks.presets [--cases snow_sharp snow lego room 7scenes_shaped]
                                    [--presets default fast accurate] [--noise 2,1] [--rounds 2] [--out FILE]

The cases, queries and priors of ``benchmarks/throughput.py`` (real photos first). A preset is a name of
``refine.config.PRESETS`` with optional overrides, ``name:field=value,field=value`` (e.g. ``fast:polish_max_side=240``).
Per case each preset refines the queries once untimed (kernel loading), then ``--rounds`` rounds in which every
preset refines every query one at a time (in the order given), so that each round compares the presets on the
same stretch of this shared machine. Columns: the final polish size, seconds per query (mean of the rounds), the
speed over the first preset (each round's), renders and derivative passes per query, the prior's and the returned
median error (% of the depth or cm; degrees), queries returned worse than their prior, and whether every round
returned the same poses.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import case_errors, case_priors, is_metric, load, same_poses, worse_count, write_keeping_notes
from hgsloc_plugin.refine.plan import make_plan


def parse_preset(spec: str) -> tuple[str, dict]:
    """``name[:field=value,...]`` -> (name, overrides); values as ints, floats or strings."""
    name, _, rest = spec.partition(":")

    def value(v: str):
        for kind in (int, float):
            try:
                return kind(v)
            except ValueError:
                pass
        return v

    pairs = [p.split("=", 1) for p in rest.split(",") if p]
    if any(len(p) != 2 for p in pairs):
        raise SystemExit(f"--presets: {spec!r}: overrides are field=value, separated by commas")
    return name, {k: value(v) for k, v in pairs}


def run(case: str, specs: list[str], pct: float, deg: float, rounds: int) -> list[str]:
    """The table rows of ``case``, one per preset."""
    loaded = load(case)
    if loaded is None:
        print(f"skipping {case}: data not found", file=sys.stderr)
        return []
    cam, scene, qs, bg = loaded
    priors = case_priors(case, qs, pct, deg)
    refiners = []
    for spec in specs:
        name, over = parse_preset(spec)
        refiners.append(hp.HGSLocPlugin(scene, hp.RefineConfig.preset(name, background=bg, **over)))
        refiners[-1].refine(qs[0][2], cam, priors[0])  # untimed: kernel loading, workspaces
    secs = np.zeros((rounds, len(specs)))
    results: list[list] = [[] for _ in specs]
    for r in range(rounds):
        for k, refiner in enumerate(refiners):
            t0 = time.perf_counter()
            results[k].append([refiner.refine(img, cam, p) for (_, _, img, _), p in zip(qs, priors)])
            secs[r, k] = (time.perf_counter() - t0) / len(qs)
    unit = "cm" if is_metric(case) else "% depth"
    e0 = case_errors(case, qs, priors)
    rows = []
    for k, spec in enumerate(specs):
        first = results[k][0]
        same = same_poses(first, results[k][1:])
        e1 = case_errors(case, qs, [x.pose for x in first])
        worse = worse_count(e0, e1)
        plan = make_plan(refiners[k].config, scene, cam, priors[0], hp.QueryPrior())
        speed = " / ".join(f"{secs[r, 0] / secs[r, k]:.2f}" for r in range(rounds))
        rows.append(f"| {case} | `{spec}` | {plan.cam_polish.width}x{plan.cam_polish.height} | "
                    f"{secs[:, k].mean():.2f} | {speed}x | {np.mean([x.renders for x in first]):.0f} | "
                    f"{np.mean([x.derivative_passes for x in first]):.1f} | "
                    f"{np.median(e0[:, 0]):.3f} / {np.median(e0[:, 1]):.2f} {unit} | "
                    f"{np.median(e1[:, 0]):.3f} / {np.median(e1[:, 1]):.3f} | {worse} / {len(qs)} | "
                    f"{'yes' if same else 'NO'} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["snow_sharp", "snow", "lego", "room", "7scenes_shaped"])
    ap.add_argument("--presets", nargs="+", default=["default", "fast", "accurate"],
                    help="preset names with optional overrides (name:field=value,...); the first is the reference")
    ap.add_argument("--noise", default="2,1", help="prior size: percent of the median depth (cm on the room), "
                                                   "degrees")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path, help="also write the table as Markdown here")
    a = ap.parse_args()
    if a.rounds < 1:
        ap.error("--rounds must be at least 1")
    pct, deg = (float(x) for x in a.noise.split(","))
    arch = hp.init()
    head = [f"Backend {arch}; priors {pct:g} % of the depth (room: {pct:g} cm) / {deg:g} deg (7scenes_shaped: "
            f"ACE's and Marepo's errors); {a.rounds} rounds, the presets in turn; speed against `{a.presets[0]}`.",
            "", "| case | preset | polish size | s / query | speed | renders / query | derivative passes "
            "| prior median t / R | returned median t / R | worse | same poses |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    rows = [row for case in a.cases for row in run(case, a.presets, pct, deg, a.rounds)]
    if a.out:
        write_keeping_notes(a.out, ["# Presets (`benchmarks/presets.py`)", "",
                                    f"Regenerate: `python -m benchmarks.presets --out {a.out}`.", "", *head, *rows])


if __name__ == "__main__":
    main()
