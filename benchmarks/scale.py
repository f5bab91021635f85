"""Scale-out: queries per second in this process and in worker processes sharing the machine, in one run.

Usage: python -m benchmarks.scale [--case 7scenes_shaped] [--queries 12] [--processes 2] [--workers 1 2]
                                  [--threads 1] [--noise 2,1] [--out FILE]

The queries of ``benchmarks/throughput.py``'s ``--case`` (default: the 7-Scenes-shaped job, ``--queries``
photo-degraded room queries at 640x480 with ACE's and Marepo's 7-Scenes errors as priors), the default settings,
refined:
- in this process, one query at a time, then in lockstep batches (the backend's default size);
- for each ``--processes`` count, in that many plain processes started together (no Ray), process k refining
  queries k, k + N, ... in lockstep batches: what processes sharing one device give, where Ray is not installed;
- for each ``--workers`` count, on that many local Ray workers (skipped without Ray), each in lockstep batches
  of its backend's default size; with GPUs every worker runs on CUDA and they share the GPUs
  (``distributed.worker_resources``).
On a GPU a query's host side (Python, launches, read-backs) outlasts its kernels, so processes sharing the device
keep it busy. Worker processes run ``--threads`` CPU threads each. Per mode: the start (processes: until the
last one began refining, after starting Taichi, loading the data and one warm-up query; Ray: until the first
result; this process is warm), seconds per query (processes: from the first one's first refinement to the last
one's end; Ray: the whole call, its workers' start included: results come back a chunk at a time), queries per
second, the speed over one at a time, and whether every pose equals the one at a time bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import (
    ROOT,
    case_priors,
    load,
    write_keeping_notes,
)
from benchmarks.machine import module_command
from hgsloc_plugin.core.backend import default_batch_size
from hgsloc_plugin.run.batch import as_queries, run_batch

HEADER = ("| mode | start (s) | s / query | queries / s | speed | same poses |\n"
          "|---|---|---|---|---|---|")


def timed(fn, n: int):
    """(results, seconds until the first result, seconds per query over the whole call) of ``fn(on_result)``
    refining ``n`` queries."""
    first = []
    t0 = time.perf_counter()
    out = fn(lambda q, r: first.append(time.perf_counter() - t0) if not first else None)
    return out, first[0], (time.perf_counter() - t0) / n


def load_items(case: str, queries: int, noise: str):
    """(camera, scene, background, items for ``run_batch``) of ``case``; exits when its data is missing."""
    pct, deg = (float(x) for x in noise.split(","))
    loaded = load(case, shaped_queries=queries, room_queries=queries)
    if loaded is None:
        sys.exit(f"{case}: data not found")
    cam, scene, qs, bg = loaded
    priors = case_priors(case, qs, pct, deg)
    return cam, scene, bg, [(img, cam, p, n) for (n, _, img, _), p in zip(qs, priors)]


def child(a) -> None:
    """``--child K N``: refine queries K, K + N, ... in lockstep batches; print one JSON line: the seconds from
    the first refinement to the last and each query's (index, pose as 7 numbers)."""
    k, n = a.child
    hp.init(cpu_threads=a.threads)
    cam, scene, bg, items = load_items(a.case, a.queries, a.noise)
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    mine = list(range(k, len(items), n))
    refiner.refine(items[mine[0]][0], cam, items[mine[0]][2])  # warm-up, as the parent's
    t0 = time.time()
    got = refiner.refine_many([items[i] for i in mine], progress=False)
    print(json.dumps({"start": t0, "seconds": time.time() - t0,
                      "poses": [[i, r.pose.as_array().tolist()] for i, r in zip(mine, got)]}), flush=True)


def processes(a, n: int):
    """``n`` child processes started together: (poses by query index, seconds until the last one began refining,
    seconds per query from the first one's first refinement to the last one's end)."""
    cmd = [*module_command(__file__), "--case", a.case, "--queries", str(a.queries), "--noise", a.noise,
           "--threads", str(a.threads), "--child"]
    t0 = time.time()
    procs = [subprocess.Popen(cmd + [str(k), str(n)], stdout=subprocess.PIPE, text=True, cwd=ROOT) for k in range(n)]
    outs = [p.communicate()[0] for p in procs]
    if any(p.returncode for p in procs):
        sys.exit(f"a child process failed: exit statuses {[p.returncode for p in procs]}")
    runs = [json.loads(o.strip().splitlines()[-1]) for o in outs]
    poses = {i: np.array(v) for r in runs for i, v in r["poses"]}  # JSON floats round-trip exactly
    begin = min(r["start"] for r in runs)
    end = max(r["start"] + r["seconds"] for r in runs)
    return poses, max(r["start"] for r in runs) - t0, (end - begin) / len(poses)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="7scenes_shaped", help="a case of benchmarks/throughput.py")
    ap.add_argument("--queries", type=int, default=12, help="queries of the room cases (the photo cases have theirs)")
    ap.add_argument("--processes", type=int, nargs="*", default=[2], help="plain process counts to run")
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2], help="Ray worker counts to run")
    ap.add_argument("--threads", type=int, default=1, help="CPU threads per worker process")
    ap.add_argument("--child", type=int, nargs=2, metavar=("K", "N"), help=argparse.SUPPRESS)
    ap.add_argument("--noise", default="2,1", help="prior size: percent of the median depth (cm on the room), "
                                                   "degrees (not the 7-Scenes-shaped job's)")
    ap.add_argument("--out", type=Path, help="also write the table as Markdown here")
    a = ap.parse_args()
    if a.child:
        return child(a)
    arch = hp.init()
    cam, scene, bg, items = load_items(a.case, a.queries, a.noise)
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    refiner.refine(items[0][0], cam, items[0][2])  # warm-up: kernel loading, workspaces
    bs = default_batch_size()

    def call(**kw):
        return lambda on_result: run_batch(refiner, as_queries(items), progress=False, on_result=on_result, **kw)

    head = [f"Case {a.case}: {len(items)} queries, {scene.num_gaussians:,} Gaussians; this process on {arch} "
            f"({os.cpu_count()} CPUs); Ray workers of {a.threads} thread(s) each.", "", HEADER]
    print("\n".join(head), flush=True)
    n = len(items)
    ref, _, t_seq = timed(call(batch_size=1), n)
    rows = []

    def row(mode: str, got, start: float, per_query: float) -> None:
        """``got``: results in input order, or poses by query index as [7] arrays."""
        poses = [got[i] for i in range(len(ref))] if isinstance(got, dict) else [r.pose.as_array() for r in got]
        same = all(x.pose.as_array().tobytes() == p.tobytes() for x, p in zip(ref, poses))
        rows.append(f"| {mode} | {start:.1f} | {per_query:.2f} | {1 / per_query:.2f} | {t_seq / per_query:.2f}x "
                    f"| {'yes' if same else 'NO'} |")
        print(rows[-1], flush=True)

    row("this process, one at a time", ref, 0.0, t_seq)
    got, _, per_query = timed(call(batch_size=bs), n)
    row(f"this process, batches of {bs}", got, 0.0, per_query)
    for count in a.processes:
        row(f"{count} processes, batches of {bs}", *processes(a, count))
    try:
        import ray
    except ImportError:
        ray = None
        if a.workers:
            print("Ray not installed: no Ray rows", file=sys.stderr)
    for workers in a.workers if ray else []:
        ray.init(num_cpus=max(1, workers * a.threads), include_dashboard=False, log_to_driver=False)
        try:
            from hgsloc_plugin.run.distributed import worker_resources

            res, worker_arch = worker_resources(ray.cluster_resources().get("GPU", 0), workers, a.threads)
            # ray_results through run_batch: each worker's own default batch size
            got, start, per_query = timed(call(workers=workers), n)
        finally:
            ray.shutdown()
        share = f", {res['num_gpus']:g} GPU each" if res["num_gpus"] else ""
        row(f"Ray, {workers} worker(s) on {worker_arch}{share}", got, start, per_query)
    if a.out:
        write_keeping_notes(a.out, ["# Scale-out (`benchmarks/scale.py`)", "",
                                    f"Regenerate: `python -m benchmarks.scale --out {a.out}`.", "", *head, *rows])


if __name__ == "__main__":
    main()
