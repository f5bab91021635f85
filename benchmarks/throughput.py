"""Throughput: queries per second of a preset's refinement, and each query's time in units of one plain render.

Usage: python -m benchmarks.throughput [--cases snow_sharp snow lego room room_x20 7scenes_shaped] [--noise 2,1]
                                       [--batch-size N] [--shaped-queries N] [--layout backend|cuda] [--rounds N]
                                       [--config PRESET] [--out FILE]

One process; per case, ``--rounds`` (2) rounds of the queries one at a time and then in lockstep batches, each
round's batched speed against the sequential queries just before it; ``--config`` the preset (default: the
default). Cases, real photos first:
- ``snow_sharp`` / ``snow``: the 6 real snow photos on the good and the imperfect map; priors of exactly ``--noise``
  (% of the query's median depth, degrees) in random directions;
- ``lego``: 5 held-out renders (white background), the same priors;
- ``room`` / ``room_x20``: the demo room (49k Gaussians) and the room densified 20x (975k), 3 photo-degraded
  queries at 320x240;
- ``7scenes_shaped``: a 7-Scenes-shaped job: the room, ``--shaped-queries`` (6) photo-degraded queries at 640x480
  (7-Scenes' size), priors with the camera-frame errors of the real ACE (first half) and Marepo (second half)
  7-Scenes estimates against the SfM pseudo ground truth (``../shared/data/poses/7scenes``, one drawn per query;
  metres, as 7-Scenes).

Columns: Gaussians, scoring size, one plain render of one pose at the final scoring size (ms, on the renderer the
refinement uses, in this process: after each sequential query the median of 3, their mean) and per pose of a
12-pose batch (before and after the timed queries, the mean of the two), seconds per query, queries per second,
time per query in render-times (machine-independent: the refinement's cost in single plain renders of the same
map and size), renders and derivative passes per query, the prior's and the returned median error (% depth or cm;
degrees), queries made worse: all for one query at a time (``refine_many(batch_size=1)``; times: the mean of the
rounds). Then the same queries in one lockstep batch (``--batch-size``, default the backend's:
``hgsloc_plugin/run/lockstep.py``; after an untimed batch of the first ``--batch-size`` queries, as the sequential
queries follow an untimed one): seconds per query, speed over sequential (each round's), device calls per query
sequential -> batched (the host-device round trips: a batched launch counts once), Taichi kernel launches per query
sequential -> batched (uploads and read-backs included: each costs the host tens of microseconds whatever the
device), the host's milliseconds per query outside Taichi's C++ launches, sequential -> batched (Python, NumPy,
image loading and Taichi's Python launch path: what one process spends per query on any device, however fast its
kernels; on the CPU the Python right after a kernel runs with cold caches, so more than it would beside a GPU),
whether every returned pose of every round, sequential and batched, equals the first round's sequential one bit
for bit, and the share of the CPU time the hypervisor took during the sequential and the batched queries
(``benchmarks/machine.py``: the render-times and the batched speed move with it). A second table splits each
query's time (render-times, sequential) by stage: the polish and the lattice search (usual and wide levels) per
scoring size, the acceptance rule (its one-pixel moves), and the rest (plan, working set, query upload); on the
CPU, where a launch runs its kernel, a third by kernel (the seconds in each kernel's launches, named by the
``@ti.kernel`` function, ``kernels/``), the rest being the host's.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import (
    case_errors,
    case_priors,
    is_metric,
    load,
    render_ms,
    same_poses,
    stage_clock,
    worse_count,
    write_keeping_notes,
)
from benchmarks.machine import StealClock
from hgsloc_plugin.core.backend import default_batch_size
from hgsloc_plugin.kernels.config import CUDA_LAYOUT  # (--layout cuda)
from hgsloc_plugin.kernels.launch import timed_launches
from hgsloc_plugin.refine.config import PRESETS
from hgsloc_plugin.refine.plan import make_plan
from hgsloc_plugin.run.batch import as_queries
from hgsloc_plugin.run.lockstep import Lockstep, refine_queries


def batched(refiner: hp.HGSLocPlugin, items: list, batch_size: int, union_limit: float | None = None,
            gate: Lockstep | None = None) -> tuple[list, float, tuple[int, int]]:
    """The queries in lockstep batches (``union_limit``: ``Lockstep``'s, None: its default; ``gate``: one that
    ran before, whose device arrays this run reuses as a long job's later batches do): (results in input order,
    seconds per query, the device calls requested and launched in this run)."""
    gate = gate or Lockstep(batch_size, union_limit)
    before = (gate.requests, gate.launches)
    t0 = time.perf_counter()
    pairs = sorted(refine_queries(refiner, as_queries(items), gate=gate), key=lambda qr: qr[0].index)
    sec = (time.perf_counter() - t0) / len(items)
    return [r for _, r in pairs], sec, (gate.requests - before[0], gate.launches - before[1])


def run(case: str, pct: float, deg: float, batch_size: int, shaped_queries: int = 6,
        raster: hp.RasterConfig | None = None, union_limit: float | None = None,
        rounds: int = 2, preset: str = "default") -> tuple[str, str, str] | None:
    loaded = load(case, shaped_queries)
    if loaded is None:
        print(f"skipping {case}: data not found", file=sys.stderr)
        return None
    cam, scene, qs, bg = loaded
    unit = "cm" if is_metric(case) else "% depth"
    priors = case_priors(case, qs, pct, deg)
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig.preset(preset, background=bg), raster=raster)
    refiner.refine(qs[0][2], cam, priors[0])  # warm-up: kernel loading, workspaces
    before = render_ms(refiner, cam, priors[0], singles=0)[1]
    items = [(img, cam, p, n) for (n, _, img, _), p in zip(qs, priors)]
    n = len(items)
    # untimed: the batched launches' workspaces (passes and line searches of several poses) grow once per process,
    # as the sequential path's did in its warm-up query (room: 88 buffers made in a first batch, 29 in the next),
    # and the gate makes its query slots once per job (the timed batches reuse it, as a long job's later ones do)
    gate = Lockstep(batch_size, union_limit)
    batched(refiner, items[:batch_size], batch_size, gate=gate)
    # rounds of the sequential queries, then the batch: each round's batched speed is against the sequential
    # queries run just before it (this shared machine's speed drifts by 10-20 % within minutes)
    runs, units, seq_sec, bat_sec = [], [], [], []
    seq_launches, batch_launches, device_calls = [0, 0.0], [0, 0.0], [0, 0]
    seq_kernels: dict[str, float] = defaultdict(float)  # seconds per kernel name, sequential rounds
    steal, steal_b = [], []
    with stage_clock(refiner) as spent:
        for _ in range(rounds):
            results, sec = [], 0.0
            with timed_launches() as launches, StealClock() as clock:
                for item in items:
                    t0 = time.perf_counter()
                    results += refiner.refine_many([item], progress=False, batch_size=1)
                    sec += time.perf_counter() - t0
                    # the unit right after each query, so that it sees the machine the query ran on (one measurement
                    # on each side of the queries moved by up to 50 % on this shared machine); not counted
                    with timed_launches():  # the unit's own launches count there, not in the queries'
                        units.append(render_ms(refiner, cam, priors[0], singles=3, batch=False)[0])
            seq_sec.append(sec / n)
            seq_launches = [seq_launches[0] + launches.count, seq_launches[1] + launches.seconds]
            for k, v in launches.by_kernel.items():
                seq_kernels[k] += v
            steal.append(clock.share)
            sequential_stages = dict(spent)  # the stage split is the sequential queries'
            with timed_launches() as launches, StealClock() as clock:
                together, sec_b, calls = batched(refiner, items, batch_size, gate=gate)
            spent.clear()
            spent.update(sequential_stages)
            bat_sec.append(sec_b)
            batch_launches = [batch_launches[0] + launches.count, batch_launches[1] + launches.seconds]
            device_calls = [a + b for a, b in zip(device_calls, calls)]
            steal_b.append(clock.share)
            runs += [results, together]
    sec, sec_b = float(np.mean(seq_sec)), float(np.mean(bat_sec))
    ms, ms_batch = float(np.mean(units)), float(np.mean([before, render_ms(refiner, cam, priors[0], singles=0)[1]]))
    per_query = rounds * n
    host_ms = [1000 * (sec - seq_launches[1] / per_query), 1000 * (sec_b - batch_launches[1] / per_query)]
    requests, launches = (c / rounds for c in device_calls)
    results = runs[0]
    same = same_poses(results, runs[1:])
    speeds = " / ".join(f"{a / b:.2f}" for a, b in zip(seq_sec, bat_sec))
    spent = {k: v / rounds for k, v in spent.items()}
    e0, e1 = case_errors(case, qs, priors), case_errors(case, qs, [r.pose for r in results])
    worse = worse_count(e0, e1)
    plan = make_plan(refiner.config, scene, cam, priors[0], hp.QueryPrior())
    row = (f"| {case} | {scene.num_gaussians:,} | {plan.cam_final.width}x{plan.cam_final.height} | {ms:.1f} / "
           f"{ms_batch:.1f} | "
           f"{sec:.2f} | {1 / sec:.2f} | {1000 * sec / ms:.0f} | {np.mean([r.renders for r in results]):.0f} | "
           f"{np.mean([r.derivative_passes for r in results]):.1f} | "
           f"{np.median(e0[:, 0]):.3f} / {np.median(e0[:, 1]):.2f} {unit} | "
           f"{np.median(e1[:, 0]):.3f} / {np.median(e1[:, 1]):.3f} | {worse} / {len(items)} | "
           f"{sec_b:.2f} | {speeds}x | {requests / n:.0f} -> {launches / n:.0f} | "
           f"{seq_launches[0] / per_query:.0f} -> {batch_launches[0] / per_query:.0f} | "
           f"{host_ms[0]:.0f} -> {host_ms[1]:.0f} | "
           f"{'yes' if same else 'NO'} | {100 * np.mean(steal):.0f} / {100 * np.mean(steal_b):.0f} |")
    print(row, flush=True)
    unit = len(items) * ms / 1000  # seconds of one render, per query
    parts = {k: v / unit for k, v in sorted(spent.items(), key=lambda kv: -kv[1])}
    rest = 1000 * sec / ms - sum(parts.values())
    split = f"| {case} | " + ", ".join(f"{k} {v:.0f}" for k, v in parts.items()) + f", rest {rest:.0f} |"
    by_kernel = {k: v / rounds / unit for k, v in sorted(seq_kernels.items(), key=lambda kv: -kv[1])}
    host = 1000 * sec / ms - sum(by_kernel.values())
    kernels = (f"| {case} | " + ", ".join(f"{k} {v:.1f}" for k, v in by_kernel.items() if v >= 0.05)
               + f", host {host:.1f} |")
    return row, split, kernels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["snow_sharp", "snow", "lego", "room", "room_x20", "7scenes_shaped"])
    ap.add_argument("--noise", default="2,1", help="prior size: percent of the median depth (cm on the room), "
                                                   "degrees")
    ap.add_argument("--batch-size", type=int, help="queries per lockstep batch (default: the backend's)")
    ap.add_argument("--shaped-queries", type=int, default=6, help="queries of the 7-Scenes-shaped job")
    ap.add_argument("--out", type=Path, help="also write the table as Markdown here")
    ap.add_argument("--layout", choices=["backend", "cuda"], default="backend",
                    help="renderer settings: the backend's defaults, or CUDA's forced on any backend (its launch "
                         "counts; slow on the CPU)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of sequential then batched queries per case")
    ap.add_argument("--config", default="default", choices=sorted(PRESETS), help="the refinement's preset")
    ap.add_argument("--union-limit", type=float,
                    help="Lockstep's union_limit (default: its own): 1 keeps the working sets of a large map's "
                         "queries in launches of their own")
    a = ap.parse_args()
    pct, deg = (float(x) for x in a.noise.split(","))
    arch = hp.init()
    raster = hp.RasterConfig(**CUDA_LAYOUT) if a.layout == "cuda" else None
    bs = a.batch_size or default_batch_size()
    head = [f"Backend {arch}; priors {pct:g} % of the depth (room: {pct:g} cm) / {deg:g} deg (7scenes_shaped: "
            f"ACE's and Marepo's errors); {a.rounds} rounds of sequential, then batched ({bs} queries in lockstep)"
            f"{'; CUDA layout ' + str(CUDA_LAYOUT) if raster else ''}"
            f"{'; union limit ' + format(a.union_limit, 'g') if a.union_limit else ''}"
            f"{'; preset ' + a.config if a.config != 'default' else ''}.", "",
            "| case | Gaussians | scoring size | render (ms: one pose / per pose of 12) | s / query | queries / s "
            "| render-times / query "
            "| renders / query | derivative passes | prior median t / R | returned median t / R | worse "
            "| batched s / query | batched speed | device calls / query | kernel launches / query "
            "| host ms / query | same poses | steal %: sequential / batched |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(head), flush=True)
    if a.rounds < 1:
        ap.error("--rounds must be at least 1")
    done = [r for r in (run(c, pct, deg, bs, a.shaped_queries, raster, a.union_limit, a.rounds, a.config)
                        for c in a.cases) if r]
    rows = [r for r, _, _ in done]
    split = ["", "Where a query's time goes (render-times per query, by stage):", "", "| case | stages |", "|---|---|",
             *(s for _, s, _ in done)]
    if arch != "cuda":  # a CPU launch runs its kernel; a CUDA one only enqueues it
        split += ["", "By kernel (render-times per query in each kernel's launches, then the host's share):", "",
                  "| case | kernels |", "|---|---|", *(k for _, _, k in done)]
    print("\n".join(split), flush=True)
    if a.out:
        write_keeping_notes(a.out, ["# Throughput (`benchmarks/throughput.py`)", "",
                                    f"Regenerate: `python -m benchmarks.throughput --out {a.out}`.", "", *head, *rows,
                                    *split])


if __name__ == "__main__":
    main()
