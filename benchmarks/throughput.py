"""Throughput: queries per second of a preset's refinement, and each query's time in units of one plain render.

Usage: python benchmarks/throughput.py [--cases snow_sharp snow lego room room_x20 7scenes_shaped] [--noise 2,1]
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
import contextlib
import math
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from machine import StealClock  # noqa: E402
from real_photos import load_dataset, localizer_errors, shaped_prior, worse_count, write_keeping_notes  # noqa: E402

import hgsloc_plugin as hp  # noqa: E402
from hgsloc_plugin.core.backend import default_batch_size  # noqa: E402
from hgsloc_plugin.evaluation.noise import se3_noise  # noqa: E402
from hgsloc_plugin.kernels.config import CUDA_LAYOUT  # noqa: E402  (--layout cuda)
from hgsloc_plugin.refine.config import PRESETS  # noqa: E402
from hgsloc_plugin.refine.plan import make_plan  # noqa: E402
from hgsloc_plugin.run.batch import as_queries  # noqa: E402
from hgsloc_plugin.run.lockstep import Lockstep, refine_queries  # noqa: E402


def room_case(k: int, n: int = 3, scale: float = 1.0):
    """(camera, scene, [(name, truth, image, median depth)], background) of the room densified ``k`` times, ``n``
    photo-degraded queries of the undensified room at ``scale`` times the demo's 320x240."""
    from hgsloc_plugin.cli.demo.queries import degrade, query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify, make_room_scene
    from hgsloc_plugin.refine.plan import median_depth

    room, cam = make_room_scene(), QUERY_CAMERA.scaled(scale)
    gts = query_poses(n, seed=1)
    imgs = [degrade(im, np.random.default_rng(1000 + i)) for i, im in enumerate(hp.render(room, cam, gts))]
    scene = densify(room, k) if k > 1 else room
    qs = [(f"room{i}", g, im, median_depth(scene, cam, g)) for i, (g, im) in enumerate(zip(gts, imgs))]
    return cam, scene, qs, (0.0, 0.0, 0.0)


def shaped_priors(qs) -> list[hp.Pose]:
    """The 7-Scenes-shaped job's priors: ACE's errors for the first half of ``qs``, Marepo's for the rest."""
    rng = np.random.default_rng(500)
    by_method = {m: localizer_errors(m) for m in ("ace", "marepo")}  # each parses every 7-Scenes pose file: once
    out = []
    for k, (_, g, _, _) in enumerate(qs):
        errs = by_method["ace" if k < len(qs) // 2 else "marepo"]
        out.append(shaped_prior(g, errs[int(rng.integers(len(errs)))], 2.0))  # metric: the errors as they are
    return out


def load(case: str, shaped_queries: int = 6, room_queries: int = 3):
    """(camera, scene, [(name, truth, image, median depth)], background) of ``case``, or None without its data;
    ``shaped_queries`` / ``room_queries``: the query count of the 7-Scenes-shaped job / the room cases."""
    if case == "7scenes_shaped":  # the room, queries at 640x480 (7-Scenes' size)
        return room_case(1, n=shaped_queries, scale=2.0)
    if case.startswith("room"):
        return room_case(int(case.split("_x")[1]) if "_x" in case else 1, n=room_queries)
    out = load_dataset(case)
    if out is None:
        return None
    cam, scene, qs, bg = out
    return cam, scene, qs[:5] if case == "lego" else qs, bg


def is_metric(case: str) -> bool:
    """Whether ``case``'s priors and errors are in scene units (the room: metres) rather than % of the depth."""
    return case.startswith("room") or case == "7scenes_shaped"


def case_priors(case: str, qs, pct: float, deg: float, seed: int = 7) -> list[hp.Pose]:
    """The priors of ``case``'s queries ``qs`` (``load``'s): exactly ``pct`` % of each query's median depth (cm on
    the room) and ``deg`` degrees in random directions drawn from ``seed``; the 7-Scenes-shaped job's from ACE's
    and Marepo's errors."""
    if case == "7scenes_shaped":
        return shaped_priors(qs)
    rng = np.random.default_rng(seed)
    return [se3_noise(g, deg, pct / 100 * (1.0 if is_metric(case) else d), rng) for _, g, _, d in qs]


def case_errors(case: str, qs, poses: list[hp.Pose]) -> np.ndarray:
    """[n, 2]: each pose's error to its query's truth (``qs``: ``load``'s), the centre in % of the query's median
    depth (cm on the room) and the rotation in degrees."""
    scale = [(100.0 if is_metric(case) else 100.0 / d) for _, _, _, d in qs]
    errors = [p.errors_to(g) for (_, g, _, _), p in zip(qs, poses)]
    return np.array([[t * s, r] for (t, r), s in zip(errors, scale)])


def same_poses(first: list, others: list[list]) -> bool:
    """Whether every result list of ``others`` returned ``first``'s poses bit for bit."""
    return all(a.pose.as_array().tobytes() == b.pose.as_array().tobytes() for other in others
               for a, b in zip(first, other))


def render_ms(refiner: hp.HGSLocPlugin, cam: hp.Camera, prior: hp.Pose, singles: int = 15,
              batch: bool = True) -> tuple[float, float]:
    """One plain render at the final scoring size on the refinement's renderer: (ms for one pose, median of
    ``singles``, nan for none; ms per pose of a 12-pose batch, nan without ``batch``)."""
    plan = make_plan(refiner.config, refiner.scene, cam, prior, hp.QueryPrior())
    renderer = refiner._working_set(plan)
    poses = [se3_noise(prior, 0.2, 0.01 * plan.depth, np.random.default_rng(s)) for s in range(12)]
    bg = refiner.config.background
    renderer.render_full(plan.cam_final, poses if batch else poses[:1], bg)  # warm-up (and the working set)
    single = []
    for k in range(singles):
        t0 = time.perf_counter()
        renderer.render_full(plan.cam_final, [poses[k % len(poses)]], bg)
        single.append(time.perf_counter() - t0)
    one = 1000 * float(np.median(single)) if single else math.nan
    if not batch:
        return one, math.nan
    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        renderer.render_full(plan.cam_final, poses, bg)
    return one, 1000 * (time.perf_counter() - t0) / (reps * len(poses))


@contextlib.contextmanager
def stage_clock():
    """Seconds spent per stage while inside: {"polish WxH": s, "search WxH": s, "rule": s}, by scoring size (wraps
    the route functions the refiner calls; restored on exit)."""
    from hgsloc_plugin.refine import refiner as refiner_mod
    from hgsloc_plugin.refine import routes

    spent: dict[str, float] = defaultdict(float)

    def timed(fn, key):
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[key(args) if callable(key) else key] += time.perf_counter() - t0
        return wrapper

    saved = [(routes, "polish"), (routes, "best_first"), (refiner_mod, "judge")]
    originals = [getattr(m, n) for m, n in saved]
    routes.polish = timed(routes.polish, lambda a: f"polish {a[1].width}x{a[1].height}")
    routes.best_first = timed(routes.best_first, lambda a: f"search {a[2].camera.width}x{a[2].camera.height}")
    refiner_mod.judge = timed(refiner_mod.judge, "rule")
    try:
        yield spent
    finally:
        for (m, n), f in zip(saved, originals):
            setattr(m, n, f)


@contextlib.contextmanager
def kernel_launches():
    """Taichi kernel launches while inside: a list holding their count, the seconds spent in Taichi's C++ launch
    (``Program.launch_kernel``: on the CPU the kernel's run, on CUDA the enqueue and any wait for a host array) and
    those seconds per kernel name ({name: s}), so that every launch counts once, through ``Kernel.__call__`` or a
    ``kernels/launch.py`` Launcher; a ``from_numpy`` upload and a read-back are launches too. The Python each launch
    costs before it stays outside (host time)."""
    from taichi.lang import impl
    from taichi.lang.kernel_impl import Kernel

    count = [0, 0.0, defaultdict(float)]
    program = type(impl.get_runtime().prog)
    launcher_class = sys.modules["hgsloc_plugin.kernels.launch"].Launcher  # benchmarks/ shadows the subpackages
    originals = (program.launch_kernel, launcher_class.__call__, Kernel.__call__)
    naming = threading.local()  # the kernel the launching thread is in (a Launcher's, else Taichi's own)

    def counted(self, *args, **kwargs):
        count[0] += 1
        t0 = time.perf_counter()
        try:
            return originals[0](self, *args, **kwargs)
        finally:
            dt = time.perf_counter() - t0
            count[1] += dt
            count[2][getattr(naming, "name", None) or "other"] += dt

    def named(original, name_of):
        def call(self, *args, **kwargs):
            outer = getattr(naming, "name", None)
            naming.name = outer or name_of(self)
            try:
                return original(self, *args, **kwargs)
            finally:
                naming.name = outer
        return call

    program.launch_kernel = counted
    launcher_class.__call__ = named(originals[1], lambda k: getattr(k.kernel, "__name__", "other"))
    Kernel.__call__ = named(originals[2], lambda k: getattr(k.func, "__name__", "other"))
    try:
        yield count
    finally:
        program.launch_kernel, launcher_class.__call__, Kernel.__call__ = originals


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
    with stage_clock() as spent:
        for _ in range(rounds):
            results, sec = [], 0.0
            with kernel_launches() as launches, StealClock() as clock:
                for item in items:
                    t0 = time.perf_counter()
                    results += refiner.refine_many([item], progress=False, batch_size=1)
                    sec += time.perf_counter() - t0
                    # the unit right after each query, so that it sees the machine the query ran on (one measurement
                    # on each side of the queries moved by up to 50 % on this shared machine); not counted
                    counted = [*launches[:2], defaultdict(float, launches[2])]
                    units.append(render_ms(refiner, cam, priors[0], singles=3, batch=False)[0])
                    launches[:] = counted
            seq_sec.append(sec / n)
            seq_launches = [a + b for a, b in zip(seq_launches, launches[:2])]
            for k, v in launches[2].items():
                seq_kernels[k] += v
            steal.append(clock.share)
            sequential_stages = dict(spent)  # the stage split is the sequential queries'
            with kernel_launches() as launches, StealClock() as clock:
                together, sec_b, calls = batched(refiner, items, batch_size, gate=gate)
            spent.clear()
            spent.update(sequential_stages)
            bat_sec.append(sec_b)
            batch_launches = [a + b for a, b in zip(batch_launches, launches[:2])]
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
                                    f"Regenerate: `python benchmarks/throughput.py --out {a.out}`.", "", *head, *rows,
                                    *split])


if __name__ == "__main__":
    main()
