"""The benchmarks' shared harness: the cases (real photos, lego, the room and its densified copies, the
7-Scenes-shaped job), their priors and errors, render timing, the refiner's stage clock and Markdown output (the
launch clock is the package's ``kernels.launch.timed_launches``).

Run a benchmark as a module from the repository root: ``python -m benchmarks.<name> --help``.
"""

from __future__ import annotations

import contextlib
import json
import math
import shlex
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from hgsloc_plugin.core.image import load_image
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.plan import make_plan, median_depth

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"

#: dataset -> (folder under ../shared/data, map file): snow has an imperfect map and a good one
MAPS = {"snow": ("snow", "snow.ply"), "snow_sharp": ("snow", "snow_sharp.ply"), "lego": ("lego", "lego.ply")}


def load_dataset(name: str):
    """(camera, scene, [(image name, true pose, image [H, W, 3], median depth)], background) or None."""
    folder, ply = MAPS.get(name, (name, f"{name}.ply"))
    d = DATA / folder
    if not (d / ply).exists():
        print(f"skipping {name}: {d / ply} not found", file=sys.stderr)
        return None
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(d / ply)
    white = name == "lego"
    queries = []
    for line in (d / "gt.txt").read_text().splitlines():
        t = line.split()
        gt = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
        if white:  # RGBA renders: composite on the white background the map was trained with
            from PIL import Image

            rgba = np.asarray(Image.open(d / "queries" / t[0]).convert("RGBA"), np.float32) / 255.0
            img = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        else:
            img = load_image(d / "queries" / t[0])
        queries.append((t[0], gt, img, median_depth(scene, cam, gt)))
    return cam, scene, queries, (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)


def localizer_errors(method: str, inliers: list | None = None) -> list[hp.Pose]:
    """Camera-frame errors E = T_est T_gt^-1 of a localizer on all 7-Scenes test frames (pGT frame); each
    estimate's inlier count (None where the file has none) is appended to ``inliers`` when given."""
    from hgsloc_plugin.adapters import read_poses
    from hgsloc_plugin.adapters.confidence import record_inliers

    out = []
    for scene_dir in sorted((DATA / "poses" / "7scenes").glob("*")):
        est, gt = read_poses(scene_dir / f"{method}.txt"), read_poses(scene_dir / "pgt_sfm_test.txt")
        by_key = {n.replace("/", "-"): n for n in est}
        for n, g in gt.items():
            k = by_key.get(n.replace("/", "-"))
            if k is not None and est[k] is not None and g is not None:
                out.append(est[k] @ g.inv())
                if inliers is not None:
                    inliers.append(record_inliers(est.dialect, est.record(k).tokens))
    return out


def shaped_prior(gt: hp.Pose, err: hp.Pose, depth: float) -> hp.Pose:
    """Apply a camera-frame error with its translation scaled by depth / 2 m (7-Scenes' typical depth)."""
    return hp.Pose(err.qvec, err.tvec * depth / 2.0) @ gt


def worse_count(e0: np.ndarray, e1: np.ndarray) -> int:
    """How many returned poses (errors ``e1`` [n, 2]) are further from the truth than their priors (``e0``)."""
    return int(np.sum((e1[:, 0] > e0[:, 0] + 1e-9) | (e1[:, 1] > e0[:, 1] + 1e-9)))


def regenerate_line(module_file: str) -> str:
    """The line a page starts with under its title: ``Regenerate: `python -m benchmarks.<name> <this run's
    arguments>```, for the benchmark whose file is ``module_file``."""
    args = " ".join(shlex.quote(a) for a in sys.argv[1:])
    return f"Regenerate: `python -m benchmarks.{Path(module_file).stem}{' ' + args if args else ''}`"


def write_keeping_notes(path: Path, lines: list[str], section: str = "## Findings") -> None:
    """Write ``lines`` as a Markdown file at ``path`` (atomically), keeping what the file already has from its
    first line starting with ``section`` (default: its ``## Findings``; ``"## "``: every level-2 section, for a
    benchmark whose own lines hold none): a benchmark regenerates its figures, not the discussion beside them."""
    from hgsloc_plugin.core.fileio import atomic_write_bytes

    old = path.read_text() if path.exists() else ""
    mark = "\n" + section
    notes = ["", old[old.index(mark) + 1:].rstrip("\n")] if mark in old else []
    atomic_write_bytes(path, ("\n".join(lines + notes) + "\n").encode())



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
    renderer = refiner.renderer_for(plan)
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
def stage_clock(refiner: hp.HGSLocPlugin):
    """Seconds spent by ``refiner`` in each stage while inside, summed over queries ({stage: s}): "polish WxH" per
    polish stage's size, "search WxH" per lattice level's scoring size, "rule" for the acceptance rule (read from
    its ``on_stage`` trace hook, restored on exit)."""
    spent: dict[str, float] = defaultdict(float)

    def add(stage: str, seconds: float) -> None:
        spent[stage] += seconds

    before, refiner.on_stage = refiner.on_stage, add
    try:
        yield spent
    finally:
        refiner.on_stage = before

