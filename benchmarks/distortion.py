"""Distorted photos: the snow photos seen through a lens with distortion, refined from their distorted query list
with no flag, against the same photos undistorted.

Usage: python -m benchmarks.distortion [--seeds 5 6 7 8] [--map snow_sharp.ply] [--out benchmarks/distortion.md]

Each photo is resampled as a lens of OPENCV k1 = -0.25, k2 = 0.08 and a 1.15x longer focal (so no pixel of it
lies outside the photo) would have taken it: every pixel looks where kornia's inverse lens model says. Both sets
are refined by ``hgsloc refine`` (a subprocess, as a user runs it) from the same priors, 1 % of each photo's median
depth and 0.5 deg off in random directions (one draw per photo and seed); errors in % of the median depth.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
LENS = (-0.25, 0.08, 0.0, 0.0)
ZOOM = 1.15
#: the page's description, under its title and regenerate line
PAGE_INTRO = ("The 6 snow photos resampled as a lens of OPENCV k1 = -0.25, k2 = 0.08 (focal 1.15x) would have taken "
              "them,\nrefined with `hgsloc refine` from their distorted query list with no flag, against the photos "
              "themselves; the same\npriors, 1 % of each photo's median depth and 0.5 deg off, four draws per photo "
              "(about 2 minutes on 2 cores).")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6, 7, 8])
    ap.add_argument("--map", default="snow_sharp.ply")
    ap.add_argument("--out", default=None, help="write the table as Markdown here")
    a = ap.parse_args()
    import torch
    import torch.nn.functional as F
    from kornia.geometry.calibration import undistort_points
    from PIL import Image

    import hgsloc_plugin as hp
    from hgsloc_plugin.adapters import read_poses
    from hgsloc_plugin.evaluation.noise import se3_noise
    from hgsloc_plugin.evaluation.viz import save_png
    from hgsloc_plugin.refine.plan import median_depth

    snow = DATA / "snow"
    cj = json.loads((snow / "camera.json").read_text())
    pin = hp.Camera(cj["width"], cj["height"], cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(snow / a.map)
    gt = read_poses(snow / "gt.txt")
    names = list(gt)
    k = [pin.fx * ZOOM, pin.fy * ZOOM, pin.cx, pin.cy, *LENS]
    tmp = Path(tempfile.mkdtemp())
    for kind in ("lens", "plain"):
        (tmp / kind).mkdir()
    v, u = np.mgrid[0:pin.height, 0:pin.width] + 0.5
    xy = np.stack([(u - k[2]) / k[0], (v - k[3]) / k[1]], -1).reshape(1, -1, 2)
    und = undistort_points(torch.from_numpy(xy), torch.eye(3, dtype=torch.float64)[None],
                           torch.tensor([LENS], dtype=torch.float64), num_iters=20)[0].numpy()
    grid = torch.from_numpy(np.stack([2 * (pin.fx * und[:, 0] + pin.cx) / pin.width - 1,
                                      2 * (pin.fy * und[:, 1] + pin.cy) / pin.height - 1], -1)
                            .reshape(1, pin.height, pin.width, 2)).float()
    for n in names:
        photo = np.asarray(Image.open(snow / "queries" / n).convert("RGB"), np.float32) / 255
        save_png(photo, tmp / "plain" / n)
        bent = F.grid_sample(torch.from_numpy(photo).permute(2, 0, 1)[None], grid, align_corners=False,
                             padding_mode="border")[0].permute(1, 2, 0).numpy()
        save_png(bent, tmp / "lens" / n)
    (tmp / "lens.txt").write_text("".join(f"{n} OPENCV {pin.width} {pin.height} {' '.join(map(str, k))}\n"
                                          for n in names))
    (tmp / "plain.txt").write_text("".join(f"{n} PINHOLE {pin.width} {pin.height} {pin.fx} {pin.fy} {pin.cx} "
                                           f"{pin.cy}\n" for n in names))
    depth = {n: median_depth(scene, pin, gt[n]) for n in names}
    errors: dict[str, list[float]] = {"lens": [], "plain": []}
    for seed in a.seeds:
        rng = np.random.default_rng(seed)
        priors = {n: se3_noise(gt[n], 0.5, 0.01 * depth[n], rng) for n in names}
        (tmp / "prior.txt").write_text("".join(" ".join([n] + [repr(float(x)) for x in p.as_array()]) + "\n"
                                               for n, p in priors.items()))
        for kind in errors:
            out = tmp / f"{kind}_{seed}.txt"
            p = subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli", "refine", "--scene", snow / a.map,
                                "--poses", tmp / "prior.txt", "--images", tmp / kind, "--intrinsics",
                                tmp / f"{kind}.txt", "--out", out, "--quiet", "--skip-check"],
                               capture_output=True, text=True)
            if p.returncode != 0:
                sys.exit(p.stderr)
            est = read_poses(out)
            errors[kind] += [100 * est[n].errors_to(gt[n])[0] / depth[n] for n in names]
    lines = [f"{a.map}, seeds {' '.join(map(str, a.seeds))}: {len(names)} photos x {len(a.seeds)} priors each", "",
             "| photos | N | median error (% of depth) | within 0.6 % | worst |", "|---|---|---|---|---|"]
    for kind, what in (("lens", "distorted, OPENCV query list, no flag"), ("plain", "undistorted, PINHOLE")):
        e = np.array(errors[kind])
        lines.append(f"| {what} | {e.size} | {np.median(e):.3f} | {(e < 0.6).sum()} | {e.max():.3f} |")
    print("\n".join(lines))
    if a.out:
        from benchmarks.harness import regenerate_line, write_keeping_notes

        write_keeping_notes(Path(a.out), ["# Distorted photos", "", regenerate_line(__file__), "", PAGE_INTRO, ""]
                            + lines)


if __name__ == "__main__":
    main()
