"""Cross-backend check: the same renders and refinements on this process's backend, for comparison across backends.

Usage:
    HGSLOC_ARCH=cuda python -m benchmarks.backends --out cuda.json
    HGSLOC_ARCH=cpu  python -m benchmarks.backends --out cpu.json
    python -m benchmarks.backends --compare cpu.json cuda.json [--md FILE]

The same code runs on either backend (``hp.init``); this script records what one backend gives, and
``--compare`` sets two records side by side. Real photos first:
- ``../shared/data/snow``: the 6 real photos refined from two prior draws (2 % of depth / 1 deg and 5 % / 2 deg,
  camera-frame, seeds as in ``real_photos.py``), twice each in one process (the two passes must return the same
  poses: determinism on this backend); per query the returned pose, its error against the SfM pose, accepted,
  route, renders, seconds.
- ``../shared/data/lego``: the 15 held-out renders from 0.025 units / 1 deg priors, once.
- renders of snow, lego and donut (``../shared/data/scenes``) at their true / fixed poses, full camera size,
  stored in ``<out>.npz``; ``--compare`` gives the PSNR of one backend's images against the other's.
The first refinement of the process is timed apart (kernel compilation or loading; "warm-up").
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import ROOT
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.render.lod import psnr

PRIORS = {"snow": ((2, 1.0), (5, 2.0)), "lego": ((1, 1.0),)}  # (% of depth, or 0.025 units per 1, deg)


def _device_name(arch: str) -> str:
    if arch == "cuda":
        try:
            import torch

            return torch.cuda.get_device_name(0)
        except Exception as exc:  # noqa: BLE001 - informative only
            return f"cuda ({exc})"
    import os
    import platform

    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} threads"


def _digest(poses) -> str:
    h = hashlib.sha256()
    for p in poses:
        h.update(np.asarray(p.qvec, np.float64).tobytes())
        h.update(np.asarray(p.tvec, np.float64).tobytes())
    return h.hexdigest()[:16]


def record(dataset: str, passes: int) -> tuple[dict, dict]:
    """This backend's refinements of one dataset (a dict for JSON) and its renders (name -> [H, W, 3])."""
    from benchmarks.harness import load_dataset

    loaded = load_dataset(dataset)
    if loaded is None:
        return {}, {}
    cam, scene, queries, bg = loaded
    images = {f"{dataset}/{name}": hp.render(scene, cam, gt, bg) for name, gt, _, _ in queries[:3]}
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    t0 = time.perf_counter()
    refiner.refine(queries[0][2], cam, queries[0][1])
    warm = time.perf_counter() - t0
    rows = []
    for pct, deg in PRIORS[dataset]:
        rng = np.random.default_rng(100)
        priors = [se3_noise(gt, deg, (pct / 100 * depth) if dataset != "lego" else 0.025 * pct, rng)
                  for _, gt, _, depth in queries]
        digests = []
        for p in range(passes):
            out = []
            for (name, gt, img, depth), prior in zip(queries, priors):
                r = refiner.refine(img, cam, prior, name=name)
                unit = 100.0 / depth if dataset != "lego" else 1.0
                t0, a0 = prior.errors_to(gt)
                t1, a1 = r.pose.errors_to(gt)
                out.append({"name": name, "qvec": list(map(float, r.pose.qvec)), "tvec": list(map(float, r.pose.tvec)),
                            "prior_err": [t0 * unit, a0], "err": [t1 * unit, a1], "accepted": bool(r.accepted),
                            "route": r.route, "renders": int(r.renders), "seconds": float(r.seconds),
                            "unit": unit})
            digests.append(_digest([hp.Pose(o["qvec"], o["tvec"]) for o in out]))
            if p == 0:
                rows.append({"prior": f"{pct}{'%' if dataset != 'lego' else 'x0.025u'} / {deg:g} deg",
                             "queries": out})
            else:
                rows[-1]["seconds_again"] = [o["seconds"] for o in out]
        rows[-1]["digests"] = digests
    return {"dataset": dataset, "gaussians": scene.num_gaussians, "size": [cam.width, cam.height],
            "warm_up_s": warm, "rows": rows}, images


def run(out: Path) -> None:
    arch = hp.init()
    t_all = time.perf_counter()
    rec = {"arch": arch, "device": _device_name(arch), "datasets": []}
    images = {}
    for ds, passes in (("snow", 2), ("lego", 1)):
        r, im = record(ds, passes)
        if r:
            rec["datasets"].append(r)
            images.update(im)
            for row in r["rows"]:
                q = row["queries"]
                print(f"{arch} {ds} {row['prior']}: median err {np.median([o['err'][0] for o in q]):.3f} / "
                      f"{np.median([o['err'][1] for o in q]):.3f}, s/query {np.mean([o['seconds'] for o in q]):.3f},"
                      f" digests {row['digests']}", file=sys.stderr, flush=True)
    donut = ROOT.parent / "shared" / "data" / "scenes" / "donut.ply"
    if donut.exists():
        scene = hp.GaussianScene.from_ply(donut)
        cam = hp.Camera.from_focal(320, 240, 300.0)
        images["donut"] = hp.render(scene, cam, hp.Pose([1, 0, 0, 0], [0, 0, 4.0]))
    rec["seconds"] = time.perf_counter() - t_all
    out.write_text(json.dumps(rec, indent=1))
    np.savez_compressed(out.with_suffix(".npz"), **images)
    print(f"wrote {out} and {out.with_suffix('.npz')} ({rec['seconds']:.0f} s)", file=sys.stderr)


def compare(pa: Path, pb: Path) -> list[str]:
    a, b = json.loads(pa.read_text()), json.loads(pb.read_text())
    ia, ib = np.load(pa.with_suffix(".npz")), np.load(pb.with_suffix(".npz"))
    lines = [f"{a['arch']} ({a['device']}) vs {b['arch']} ({b['device']})\n",
             "| data | prior | median err A | median err B | same pose | max pose diff (t, deg) | "
             "accepted A / B | deterministic A / B | s / query A | s / query B | A / B |", "|" + "---|" * 11]
    for da, db in zip(a["datasets"], b["datasets"]):
        for ra, rb in zip(da["rows"], db["rows"]):
            qa, qb = ra["queries"], rb["queries"]
            diff = [hp.Pose(x["qvec"], x["tvec"]).errors_to(hp.Pose(y["qvec"], y["tvec"])) for x, y in zip(qa, qb)]
            dt = max(d[0] * x["unit"] for d, x in zip(diff, qa))
            dr = max(d[1] for d in diff)
            same = sum(d[0] * x["unit"] < 1e-3 and d[1] < 1e-3 for d, x in zip(diff, qa))
            sa, sb = np.mean([x["seconds"] for x in qa]), np.mean([y["seconds"] for y in qb])

            def med(q):
                return f"{np.median([o['err'][0] for o in q]):.3f} / {np.median([o['err'][1] for o in q]):.3f}"

            det = "/".join("yes" if len(set(r["digests"])) == 1 and len(r["digests"]) > 1 else
                           ("-" if len(r["digests"]) == 1 else "NO") for r in (ra, rb))
            lines.append(f"| {da['dataset']} ({da['gaussians']:,}) | {ra['prior']} | {med(qa)} | {med(qb)} | "
                         f"{same} / {len(qa)} | {dt:.3f} / {dr:.3f} | {sum(x['accepted'] for x in qa)} / "
                         f"{sum(y['accepted'] for y in qb)} | {det} | {sa:.3f} | {sb:.3f} | {sa / sb:.2f}x |")
        lines.append(f"| {da['dataset']} | warm-up (s) | | | | | | | {da['warm_up_s']:.1f} | {db['warm_up_s']:.1f} | |")
    lines.append("\n| render | PSNR B vs A (dB) | max abs diff |\n|---|---|---|")
    for k in ia.files:
        if k in ib.files:
            lines.append(f"| {k} | {psnr(ia[k], ib[k]):.1f} | {float(np.abs(ia[k] - ib[k]).max()):.2e} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write this backend's record here (JSON; images beside it as .npz)")
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="compare two records")
    ap.add_argument("--md", type=Path, help="with --compare: also write the table here")
    a = ap.parse_args()
    if a.compare:
        lines = compare(*a.compare)
        print("\n".join(lines))
        if a.md:
            from hgsloc_plugin.core.fileio import atomic_write_bytes

            atomic_write_bytes(a.md, ("\n".join(lines) + "\n").encode())
    elif a.out:
        run(a.out)
    else:
        ap.error("give --out or --compare")


if __name__ == "__main__":
    main()
