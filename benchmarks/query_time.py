"""Per-query time of the default refinement against another checkout's, measured in the same run.

Usage: python -m benchmarks.query_time --before DIR [--cases snow_sharp snow lego room] [--seeds 7 8]
                                       [--rounds 3] [--out FILE]

Per case (the maps, queries and priors of ``benchmarks/harness.py``: 2 % of the depth, the room 2 cm, 1 deg,
one prior per query and seed in ``--seeds``), one query at a time (``refine_many(batch_size=1)``) after an
untimed one: seconds per query and per stage (``harness.stage_clock``), the host's milliseconds per query
outside Taichi's C++ launches (``kernels.launch.timed_launches``), renders and derivative passes per query and the
returned poses; then the same in the checkout ``DIR`` (the code before a change: a ``git worktree`` with
``hgsloc_plugin/kernels`` and ``hgsloc_plugin/adapters`` linked to its ``kernels/`` and ``adapters/``, as
``startup.py --before`` needs; this script runs on both sides, each importing its side's package, which the child
reports and the parent checks). Each side runs in processes of its own, ``--rounds`` times, alternating, so both
see the same state of a shared machine; a row gives the medians over the rounds, the speed-up (before / this
checkout), the stages' seconds, the returned median errors, how many poses moved and by how much (% of the
query's median depth, degrees), and the share of the CPU time the hypervisor took meanwhile
(``benchmarks/machine.py``). ``harness.py``'s render-times compare one run's queries with one run's render;
this compares two versions of the code on the same queries.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from benchmarks.machine import alternate, before_args, before_parser, run_child, write_before_table


def child(case: str, seeds: list[int]) -> dict:
    """The timed queries in the package this process imports (the ``--child`` side), and where it lies."""
    import hgsloc_plugin as hp
    from benchmarks import harness
    from hgsloc_plugin.kernels.launch import timed_launches
    cam, scene, qs, bg = harness.load(case)
    items, truths, scale = [], [], []  # scale: % of the depth (cm on the room) per scene unit
    for seed in seeds:
        for (name, truth, image, depth), prior in zip(qs, harness.case_priors(case, qs, 2.0, 1.0, seed)):
            items.append((image, cam, prior, name))
            truths.append(truth)
            scale.append(100.0 if harness.is_metric(case) else 100.0 / depth)
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    refiner.refine(items[0][0], cam, items[0][2])  # untimed: kernel loading, workspaces
    with harness.stage_clock(refiner) as spent, timed_launches() as launches:
        t0 = time.perf_counter()
        results = refiner.refine_many(items, progress=False, batch_size=1)
        sec = time.perf_counter() - t0
    n = len(items)
    errors = [r.pose.errors_to(g) for r, g in zip(results, truths)]
    return {"checkout": str(Path(hp.__file__).resolve().parents[1]), "queries": n, "s": sec / n,
            "stages": {k: v / n for k, v in spent.items()}, "host_ms": 1000 * (sec - launches.seconds) / n,
            "launches": launches.count / n,
            "renders": float(np.mean([r.renders for r in results])),
            "passes": float(np.mean([r.derivative_passes for r in results])),
            "t_pct": [e[0] * k for e, k in zip(errors, scale)], "r_deg": [e[1] for e in errors],
            "poses": [r.pose.as_array().tolist() for r in results]}


def moved(a: dict, b: dict) -> tuple[int, float, float]:
    """(poses that differ, largest difference of the centre error in % depth, of the rotation error in degrees)."""
    differ = sum(pa != pb for pa, pb in zip(a["poses"], b["poses"]))
    dt = max(abs(x - y) for x, y in zip(a["t_pct"], b["t_pct"]))
    dr = max(abs(x - y) for x, y in zip(a["r_deg"], b["r_deg"]))
    return differ, dt, dr


def main() -> None:
    ap = before_parser(__doc__, ["snow_sharp", "snow", "lego", "room"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[7, 8], help="one prior per query and seed")
    parsed = before_args(ap, lambda a: child(a.child, a.seeds))
    if parsed is None:
        return
    a, before = parsed

    rows = ["| case | queries | s / query: before / now | speed-up | host ms / query: before / now | "
            "by stage, s: before / now | renders / query | derivative passes | returned median t / R: before / now | "
            "poses moved (largest: t % depth / R deg) | steal % |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for case in a.cases:
        args = [case, "--seeds", *map(str, a.seeds)]
        got, steal = alternate(before, a.rounds, lambda path, args=args: run_child(__file__, path, args), case,
                               show=lambda r: f"{r['s']:.3f} s / query")
        med = {s: float(np.median([r["s"] for r in got[s]])) for s in got}
        host = {s: float(np.median([r["host_ms"] for r in got[s]])) for s in got}
        b0, n0 = got["before"][0], got["now"][0]
        stages = sorted(set(b0["stages"]) | set(n0["stages"]), key=lambda k: -n0["stages"].get(k, 0.0))
        by_stage = ", ".join(f"{k} {np.median([r['stages'].get(k, 0.0) for r in got['before']]):.2f} / "
                             f"{np.median([r['stages'].get(k, 0.0) for r in got['now']]):.2f}" for k in stages)
        differ, dt, dr = moved(b0, n0)
        rows.append(f"| {case} | {n0['queries']} | {med['before']:.3f} / {med['now']:.3f} | "
                    f"{med['before'] / med['now']:.2f}x | {host['before']:.0f} / {host['now']:.0f} | {by_stage} | "
                    f"{b0['renders']:.1f} / {n0['renders']:.1f} | "
                    f"{b0['passes']:.2f} / {n0['passes']:.2f} | "
                    f"{np.median(b0['t_pct']):.3f} / {np.median(b0['r_deg']):.3f} -> "
                    f"{np.median(n0['t_pct']):.3f} / {np.median(n0['r_deg']):.3f} | "
                    f"{differ} of {n0['queries']} ({dt:.3f} / {dr:.3f}) | {100 * steal:.0f} |")
        print(rows[-1], flush=True)
    if a.out:
        write_before_table(a.out, "Per-query time against another checkout", "query_time.py",
                           f"Backend cpu; priors 2 % of the depth / 1 deg, seeds {' '.join(map(str, a.seeds))}; "
                           f"{a.rounds} processes per side and case, alternating.", rows,
                           args=f"--cases {' '.join(a.cases)} --seeds {' '.join(map(str, a.seeds))} "
                                f"--rounds {a.rounds}")


if __name__ == "__main__":
    main()
