"""Start-up benchmark: what a new process pays before its queries run at full speed.

Usage: python -m benchmarks.startup [--runs 2] [--cold] [--before DIR] [--out FILE]

Each row is a fresh Python process (as a CLI call or a new script is) that imports the package, starts Taichi,
renders one image of the demo room and refines one query (320x240, 3 cm / 1 deg prior) twice: the first
refinement loads every kernel it needs (Taichi translates each kernel's Python source in each process and then
finds the compiled kernel in its offline cache), the second runs on loaded kernels. "loading" is their
difference. One untimed process first fills the offline cache, so every timed row sees a warm disk cache, as
every run after a user's first does; with ``--cold`` each row starts from an empty offline cache instead (a
user's first run: loading is then mostly compiling).
Settings: ``memo off`` (``HGSLOC_TAICHI_MEMO=0``: Taichi's source-position formatting not memoised, the state
before ``hgsloc_plugin/core/kernel_load.py``) and ``default``; both run the same kernels. ``--before DIR`` adds a
setting that imports the package from another checkout (e.g. ``git worktree add DIR <commit>``, with
``hgsloc_plugin/kernels`` and ``hgsloc_plugin/adapters`` linked to the checkout's top-level folders as the
editable install maps them): the code before a change, measured in the same run. Rows alternate between the
settings so that the machine's load falls on all alike.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.machine import ROOT, module_command

SETTINGS = {"memo off": {"HGSLOC_TAICHI_MEMO": "0"}, "default": {}}


def child() -> dict:
    t0 = time.perf_counter()
    import numpy as np

    import hgsloc_plugin as hp
    t_import = time.perf_counter()
    hp.init()
    t_init = time.perf_counter()
    from hgsloc_plugin.cli.demo.queries import make_queries, query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.noise import apply_protocol

    room = make_room_scene()
    cam = QUERY_CAMERA
    gt = query_poses(1, seed=1)[0]
    t1 = time.perf_counter()
    img = make_queries(room, cam, [gt], seed=0)[0]
    t_render = time.perf_counter() - t1
    prior = apply_protocol(gt, "3cm,1deg", np.random.default_rng(7))
    refiner = hp.HGSLocPlugin(room)
    first = refiner.refine(img, cam, prior)
    second = refiner.refine(img, cam, prior)
    same = bool(np.array_equal(first.pose.matrix34(), second.pose.matrix34()))
    return {"import": t_import - t0, "init": t_init - t_import, "first render": t_render,
            "first refine": first.seconds, "again": second.seconds, "same pose": same,
            "total": time.perf_counter() - t0}


def run(setting: str, cold: bool = False) -> dict:
    env = dict(os.environ, **SETTINGS[setting])
    with tempfile.TemporaryDirectory(prefix="hgsloc_cold_cache_") as empty:  # removed with the kernels compiled
        if cold:
            env["HGSLOC_CACHE_DIR"] = empty
        command = module_command(__file__, other_checkout="PYTHONPATH" in SETTINGS[setting])  # --before's setting
        p = subprocess.run([*command, "--child"], capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"child failed ({setting}):\n{p.stderr[-3000:]}")
    return json.loads(p.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=2, help="processes per setting")
    ap.add_argument("--out", type=Path, help="also write the Markdown table here")
    ap.add_argument("--before", type=Path, help="another checkout to measure as the reference (see above)")
    ap.add_argument("--cold", action="store_true", help="each process starts from an empty offline cache")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child()))
        return
    if args.before:
        from benchmarks.machine import checkout_env

        SETTINGS[f"before ({args.before.name})"] = {"PYTHONPATH": checkout_env(args.before)["PYTHONPATH"]}
    if not args.cold:
        run("default")  # untimed: fills the offline cache
    rows = []
    for k in range(args.runs):
        for setting in SETTINGS:
            r = run(setting, args.cold)
            rows.append((setting, k + 1, r))
            print(f"{setting} run {k + 1}: {r}", file=sys.stderr)
    from benchmarks.harness import regenerate_line

    lines = ["# Start-up (`benchmarks/startup.py`)", "", regenerate_line(__file__), "",
             f"A fresh process each row (offline cache {'empty' if args.cold else 'warm'}): seconds to import the "
             "package, start Taichi, render the",
             "first image (demo room, 320x240) and refine one query twice; loading = first refine - the same again.",
             "", "| setting | run | import | init | first render | first refine | same query again | loading | "
             "process total | same pose |", "|---|---|---|---|---|---|---|---|---|---|"]
    for setting, k, r in rows:
        lines.append(f"| {setting} | {k} | {r['import']:.2f} | {r['init']:.2f} | {r['first render']:.2f} | "
                     f"{r['first refine']:.2f} | {r['again']:.2f} | {r['first refine'] - r['again']:.2f} | "
                     f"{r['total']:.2f} | {'yes' if r['same pose'] else 'NO'} |")
    mean = {s: {k: sum(r[k] for t, _, r in rows if t == s) / args.runs for k in ("first render", "total")}
            | {"loading": sum(r["first refine"] - r["again"] for t, _, r in rows if t == s) / args.runs}
            for s in SETTINGS}
    new = mean["default"]
    lines.append("")
    for s in SETTINGS:
        if s != "default":
            ref = mean[s]
            lines.append(f"Means, {s} -> default: kernel loading in the first query {ref['loading']:.2f} -> "
                         f"{new['loading']:.2f} s ({ref['loading'] / max(new['loading'], 1e-9):.1f}x less), "
                         f"first render "
                         f"{ref['first render']:.2f} -> {new['first render']:.2f} s, process {ref['total']:.2f} -> "
                         f"{new['total']:.2f} s.")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        from benchmarks.harness import write_keeping_notes

        write_keeping_notes(args.out, text.rstrip("\n").split("\n"))


if __name__ == "__main__":
    main()
