"""Start-up benchmark: what a new process pays before its queries run at full speed.

Usage: python benchmarks/startup.py [--runs 2] [--out FILE]

Each row is a fresh Python process (as a CLI call or a new script is) that imports the package, starts Taichi,
renders one image of the demo room and refines one query (320x240, 3 cm / 1 deg prior) twice: the first
refinement loads every kernel it needs (Taichi translates each kernel's Python source in each process and then
finds the compiled kernel in its offline cache), the second runs on loaded kernels. "loading" is their
difference. One untimed process first fills the offline cache, so every timed row sees a warm disk cache, as
every run after a user's first does.
Settings: ``memo off`` (``HGSLOC_TAICHI_MEMO=0``: Taichi's source-position formatting not memoised, the state
before ``hgsloc_plugin/kernel_load.py``) and ``default``; both run the same kernels. Rows alternate between the
settings so that the machine's load falls on both alike.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = {"memo off": {"HGSLOC_TAICHI_MEMO": "0"}, "default": {}}


def child() -> dict:
    t0 = time.perf_counter()
    import numpy as np

    import hgsloc_plugin as hp
    t_import = time.perf_counter()
    hp.init()
    t_init = time.perf_counter()
    from hgsloc_plugin.demo.queries import make_queries, query_poses
    from hgsloc_plugin.demo.run import QUERY_CAMERA
    from hgsloc_plugin.demo.scene import make_room_scene
    from hgsloc_plugin.noise import apply_protocol

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


def run(setting: str) -> dict:
    env = dict(os.environ, **SETTINGS[setting])
    p = subprocess.run([sys.executable, __file__, "--child"], capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"child failed ({setting}):\n{p.stderr[-3000:]}")
    return json.loads(p.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=2, help="processes per setting")
    ap.add_argument("--out", type=Path, help="also write the Markdown table here")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child()))
        return
    run("default")  # untimed: fills the offline cache
    rows = []
    for k in range(args.runs):
        for setting in SETTINGS:
            r = run(setting)
            rows.append((setting, k + 1, r))
            print(f"{setting} run {k + 1}: {r}", file=sys.stderr)
    lines = ["# Start-up (`benchmarks/startup.py`)", "",
             "A fresh process each row (offline cache warm): seconds to import the package, start Taichi, render the",
             "first image (demo room, 320x240) and refine one query twice; loading = first refine - the same again.",
             "", "| setting | run | import | init | first render | first refine | same query again | loading | "
             "process total | same pose |", "|---|---|---|---|---|---|---|---|---|---|"]
    for setting, k, r in rows:
        lines.append(f"| {setting} | {k} | {r['import']:.2f} | {r['init']:.2f} | {r['first render']:.2f} | "
                     f"{r['first refine']:.2f} | {r['again']:.2f} | {r['first refine'] - r['again']:.2f} | "
                     f"{r['total']:.2f} | {'yes' if r['same pose'] else 'NO'} |")
    load = {s: [r["first refine"] - r["again"] for t, _, r in rows if t == s] for s in SETTINGS}
    ref = sum(load["memo off"]) / len(load["memo off"])
    new = sum(load["default"]) / len(load["default"])
    lines += ["", f"Kernel loading in the first query (mean): memo off {ref:.2f} s, default {new:.2f} s "
              f"({ref / max(new, 1e-9):.1f}x less)."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        tmp = args.out.with_suffix(args.out.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)


if __name__ == "__main__":
    main()
