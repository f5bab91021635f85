"""Trials: the real 7-Scenes localizer errors as the test distribution, applied to many views of many scenes.

Usage: python -m benchmarks.trials [--per-cell 100] [--scenes room stripes donut lego snow_sharp snow]
    [--localizers ace glace marepo dfnet hloc] [--jobs 2] [--raw trials.jsonl] [--out benchmarks/trials.md]
    [--compare other.jsonl]; python -m benchmarks.trials --from-raw trials.jsonl [--compare other.jsonl] tabulates
    a kept run (``--compare``: trial by trial against another run's raw file, on the trials both hold).

Errors: for each localizer, the camera-frame error ``E = T_est T_gt^-1`` of every one of its 17,000 7-Scenes
poses against the SfM pseudo ground truth (``../shared/data/poses/7scenes``); a trial draws one uniformly (seeded),
with its translation scaled by the view's median depth over 2 m (7-Scenes' typical depth), and applies it to a
view's true pose. ACE / GLACE draws carry the inlier count the localizer wrote for that pose, which sets the query's
trust region and expected error as ``hgsloc refine`` does for their files (``adapters/confidence.py``). HLoc draws
get the settings of an hloc pose whose log gives at least ``HLOC_FEW_INLIERS`` PnP inliers (``hloc_trust``): the
published 7-Scenes hloc poses carry no counts, and nearly all of them are localized from many matches.

Views (errors in **cm-eq**: centre error x 200 / the view's median depth, so 1 cm-eq is the same image motion on
every scene):
- ``room``: ``SYNTHETIC_VIEWS`` random views of the demo room (``hgsloc_plugin.cli.demo``);
- ``stripes``: random views of the room's striped wall (periodic texture: a wrong minimum one stripe over);
- ``donut``: random views of ``../shared/data/scenes/donut.ply`` (a small SH-0 object);
  the three rendered by the independent PyTorch reference (``tests/reference/render_torch.py``), then degraded as
  photos (gain, gamma, blur, noise, an occluder);
- ``lego``: its 15 held-out Blender renders against a 3DGS fitted to other views;
- ``snow_sharp`` / ``snow``: the 6 real phone photos against the good and the imperfect map.

Per localizer x scene: N, recall at 1cm1deg / 2cm2deg / 5cm5deg / 10cm10deg before -> after, medians, accepted,
**worse** (the returned pose is further from the truth than the prior in centre or rotation, any amount) and
**clearly worse** (> 1 cm-eq or > 0.5 deg further), each with its one-sided 95 % upper bound (Clopper-Pearson),
calibration (share of accepted poses whose error lies within 1 / 2 / 3 sigma, centre and rotation; sigma is the
root of the covariance trace, so a calibrated 3-D Gaussian puts 61 / 99 / 100 % there), the confidence's AUC
(the probability that an accepted right answer, within 2 cm-eq and 1 deg, has a higher confidence than an accepted
wrong one), renders and seconds per query. ``--raw`` keeps one JSON line per trial (to recompute the tables or fit
a calibration), each route's judged candidate in it (``judged``: route, error in cm-eq and deg, refusal reason).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from benchmarks.machine import ROOT, module_command

if TYPE_CHECKING:
    from hgsloc_plugin.evaluation.floor import MapFloor

DATA = ROOT.parent / "shared" / "data"
LOCALIZERS = ("ace", "glace", "marepo", "dfnet", "hloc")
SCENES = ("room", "stripes", "donut", "lego", "snow_sharp", "snow")
RECALLS = ((1.0, 1.0), (2.0, 2.0), (5.0, 5.0), (10.0, 10.0))
CLEARLY_CM, CLEARLY_DEG = 1.0, 0.5
#: a right answer, for the confidence's AUC: what the confidence is the probability of (1 % of the depth, 1 deg)
RIGHT_CM, RIGHT_DEG = 2.0, 1.0
#: 7-Scenes' typical median depth: a localizer's metric error is scaled by a view's depth over this
REFERENCE_DEPTH = 2.0
SEED = 2026
#: the synthetic views' photo degradation (``demo.queries.degrade``'s arguments)
PHOTO_DEGRADATION = dict(gain=(0.85, 1.15), gamma=(0.9, 1.1), noise_std=0.015)
#: random views per synthetic scene (room, stripes, donut); localizer ``L``'s trial ``i`` takes view
#: ``(L * SYNTHETIC_VIEWS / 5 + i) % SYNTHETIC_VIEWS``: every view serves several localizers' errors, and rendering
#: the views with the reference renderer (~2 s each on one core) does not dominate the run
SYNTHETIC_VIEWS = 200
#: ``--map-floor measured``: the views of each scene the map's floor is measured on (the fixed scenes: all of theirs)
FLOOR_VIEWS = 12

#: the page's description of the views and columns, under its title and regenerate line
PAGE_INTRO = """\
Each trial draws one of a localizer's 17,000 camera-frame errors against the SfM pseudo ground truth (ACE / GLACE
with their own inlier counts, HLoc with the settings of a well-supported hloc pose), scales it to the view's depth
(cm-eq: 7-Scenes centimetres at 2 m) and applies it to a view: 200 random views each of the demo room, its
striped wall and the donut (rendered by the independent PyTorch reference, degraded as photos), lego's 15 held-out
renders, the 6 real snow photos on the good (`snow_sharp`) and the imperfect (`snow`) map. 100 trials per
localizer and scene. "worse": the returned pose further from the truth than the prior in centre or rotation, any
amount; "clearly worse": more than 1 cm-eq or 0.5 deg further; bounds one-sided 95 % (Clopper-Pearson). Errors in
cm-eq / deg; recalls at 1cm1deg / 2cm2deg / 5cm5deg / 10cm10deg (cm-eq); "within 1/2/3 sigma": share of the
accepted poses whose error lies within that many of their own sigma (a calibrated 3-D sigma holds 61 / 99 / 100 %)."""


# ---------------------------------------------------------------- statistics (no package imports: cheap to test)

def upper_bound(k: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound of a rate with ``k`` events in ``n`` trials (1.0 when n = 0)."""
    if n <= 0:
        return 1.0
    if k >= n:
        return 1.0

    def cdf(p: float) -> float:  # P(X <= k) for X ~ Binomial(n, p)
        if p <= 0.0:
            return 1.0
        if p >= 1.0:
            return 0.0
        lp, lq = math.log(p), math.log1p(-p)
        return sum(math.exp(math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * lp
                            + (n - i) * lq) for i in range(k + 1))

    lo, hi = k / n, 1.0
    for _ in range(100):  # cdf falls with p: find p where it is 1 - level
        mid = 0.5 * (lo + hi)
        if cdf(mid) > 1.0 - level:
            lo = mid
        else:
            hi = mid
    return hi


def auc(pos, neg) -> float:
    """The probability that a draw from ``pos`` scores above one from ``neg`` (ties count half): the area under
    the ROC curve of a score separating them; nan when either is empty."""
    pos, neg = np.asarray(pos, np.float64), np.asarray(neg, np.float64)
    if not (pos.size and neg.size):
        return math.nan
    return float(np.mean(pos[:, None] > neg[None, :]) + 0.5 * np.mean(pos[:, None] == neg[None, :]))


def summarise(rows: list[dict]) -> dict:
    """The table's figures for a list of trial records (``run_trial``'s dicts)."""
    n = len(rows)
    e0 = np.array([[r["t0"], r["r0"]] for r in rows], np.float64).reshape(-1, 2)
    e1 = np.array([[r["t1"], r["r1"]] for r in rows], np.float64).reshape(-1, 2)
    acc = np.array([r["accepted"] for r in rows], bool)
    moved = np.array([r["moved"] for r in rows], bool)
    worse = moved & ((e1[:, 0] > e0[:, 0] + 1e-9) | (e1[:, 1] > e0[:, 1] + 1e-9))
    clearly = (e1[:, 0] > e0[:, 0] + CLEARLY_CM) | (e1[:, 1] > e0[:, 1] + CLEARLY_DEG)
    out = {"n": n, "accepted": int(acc.sum()), "worse": int(worse.sum()), "clearly": int(clearly.sum()),
           "worse_ub": upper_bound(int(worse.sum()), n), "clearly_ub": upper_bound(int(clearly.sum()), n)}
    out["recall0"] = [float(np.mean((e0[:, 0] <= t) & (e0[:, 1] <= r))) if n else math.nan for t, r in RECALLS]
    out["recall1"] = [float(np.mean((e1[:, 0] <= t) & (e1[:, 1] <= r))) if n else math.nan for t, r in RECALLS]
    out["median0"] = [float(np.median(e0[:, i])) if n else math.nan for i in range(2)]
    out["median1"] = [float(np.median(e1[:, i])) if n else math.nan for i in range(2)]
    sig = np.array([[r["sigma_t"], r["sigma_r"]] for r in rows], np.float64).reshape(-1, 2)
    ok = acc & np.all(np.isfinite(sig), axis=1) & np.all(sig > 0, axis=1)
    out["calibrated_n"] = int(ok.sum())
    out["within"] = [[float(np.mean(e1[ok, i] <= m * sig[ok, i])) if ok.any() else math.nan for m in (1, 2, 3)]
                     for i in range(2)]
    conf = np.array([r["confidence"] for r in rows], np.float64)
    right = (e1[:, 0] <= RIGHT_CM) & (e1[:, 1] <= RIGHT_DEG)
    out["auc"] = auc(conf[acc & right], conf[acc & ~right])
    out["renders"] = float(np.mean([r["renders"] for r in rows])) if n else math.nan
    out["seconds"] = float(np.mean([r["seconds"] for r in rows])) if n else math.nan
    return out


def table(rows: list[dict], scenes, localizers) -> list[str]:
    """Markdown rows: one per localizer x scene present in ``rows``, then every localizer pooled per scene and the
    whole pool."""
    head = ["| localizer | scene | N | recall 1/2/5/10 before | after | median before | after | accepted | "
            "worse (95 % ub) | clearly worse (95 % ub) | within 1/2/3 sigma t | R | confidence AUC | renders | s / q |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(loc, scene, sel):
        if not sel:
            return None
        s = summarise(sel)
        pct = lambda xs: "/".join(f"{100 * x:.0f}" for x in xs)  # noqa: E731
        within = ["-" if s["calibrated_n"] == 0 else pct(s["within"][i]) for i in range(2)]
        return (f"| {loc} | {scene} | {s['n']} | {pct(s['recall0'])} | {pct(s['recall1'])} | "
                f"{s['median0'][0]:.2f} / {s['median0'][1]:.2f} | {s['median1'][0]:.2f} / {s['median1'][1]:.2f} | "
                f"{s['accepted']} | {s['worse']} ({100 * s['worse_ub']:.2f} %) | "
                f"{s['clearly']} ({100 * s['clearly_ub']:.2f} %) | {within[0]} | {within[1]} | "
                f"{'-' if math.isnan(s['auc']) else format(s['auc'], '.2f')} | {s['renders']:.0f} | "
                f"{s['seconds']:.2f} |")

    out = list(head)
    for loc in localizers:
        for scene in scenes:
            line = fmt(loc, scene, [r for r in rows if r["localizer"] == loc and r["scene"] == scene])
            if line:
                out.append(line)
    for scene in scenes:
        line = fmt("all", scene, [r for r in rows if r["scene"] == scene])
        if line:
            out.append(line)
    line = fmt("**all**", "**all**", rows)
    if line:
        out.append(line)
    return out


def compare(before: list[dict], after: list[dict], scenes) -> list[str]:
    """Markdown rows comparing two runs trial by trial (the trials both hold, matched by scene, localizer, view and
    error), per scene and pooled: N, recall at 2cm2deg and 5cm5deg, clearly worse, mean renders on all trials and
    on the ones ``before`` accepted from its gradient route."""
    key = lambda r: (r["scene"], r["localizer"], r["view"], r["error"])  # noqa: E731
    base = {key(r): r for r in before}
    pairs = [(base[key(r)], r) for r in after if key(r) in base]
    out = ["| scene | N | recall 2/5 before | after | clearly worse before | after | renders before | after | "
           "renders, gradient-accepted before | after |", "|---|---|---|---|---|---|---|---|---|---|"]
    for scene in [*scenes, None]:
        sel = [p for p in pairs if scene is None or p[0]["scene"] == scene]
        if not sel:
            continue
        a, b = summarise([p[0] for p in sel]), summarise([p[1] for p in sel])
        grad = [p for p in sel if p[0]["accepted"] and p[0]["route"] == "gradient"]
        fixed = [[p[k]["renders"] for p in grad] for k in (0, 1)]
        mean = [float(np.mean(x)) if x else math.nan for x in fixed]
        name = "**all**" if scene is None else scene
        out.append(f"| {name} | {len(sel)} | {100 * a['recall1'][1]:.0f}/{100 * a['recall1'][2]:.0f} | "
                   f"{100 * b['recall1'][1]:.0f}/{100 * b['recall1'][2]:.0f} | {a['clearly']} | {b['clearly']} | "
                   f"{a['renders']:.0f} | {b['renders']:.0f} | {mean[0]:.1f} | {mean[1]:.1f} |")
    return out


# ---------------------------------------------------------------- trials

@dataclass
class Trial:
    """One trial: a view of a scene and one localizer error applied to it."""

    index: int
    scene: str
    view: int
    localizer: str
    error: int  # index into the localizer's 17,000 errors


def plan_trials(scenes, localizers, per_cell: int, n_errors: dict[str, int], n_views: dict[str, int | None],
                seed: int = SEED) -> list[Trial]:
    """The trials, in a fixed order: per scene and localizer ``per_cell``, each drawing an error uniformly; views
    cycle through a data set's fixed views, or through ``SYNTHETIC_VIEWS`` random ones (``n_views`` None). Each cell
    draws from its own seeded stream, so a run's cells are the first trials of a run with a larger ``per_cell``
    (a quick run compares with a full one trial by trial) and do not depend on which other cells run."""
    out = []
    for scene in scenes:
        for loc in localizers:
            rng = np.random.default_rng([seed, SCENES.index(scene), LOCALIZERS.index(loc)])
            nv = n_views[scene]
            for i in range(per_cell):
                first = LOCALIZERS.index(loc) * SYNTHETIC_VIEWS // len(LOCALIZERS)
                view = (first + i) % SYNTHETIC_VIEWS if nv is None else i % nv
                out.append(Trial(len(out), scene, view, loc, int(rng.integers(n_errors[loc]))))
    return out


def localizer_errors(method: str):
    """(errors [M] as camera-frame ``Pose``s, inlier counts [M] or None) of a localizer on all 7-Scenes test
    frames, in the pGT files' order."""
    from benchmarks import harness

    counts: list = []
    errs = harness.localizer_errors(method, counts)
    return errs, (counts if any(c is not None for c in counts) else None)


class Views:
    """A scene's map, camera, background and views (true pose, query image [H, W, 3], median depth), made lazily:
    synthetic views are rendered by the reference renderer when first asked for."""

    def __init__(self, name: str):
        import hgsloc_plugin as hp
        from hgsloc_plugin.cli.demo.scene import make_room_scene

        self.name, self.fixed, self.bg = name, None, (0.0, 0.0, 0.0)
        if name in ("room", "stripes"):
            self.scene, self.cam = make_room_scene(0), hp.Camera.from_fov(320, 240, 60.0)
        elif name == "donut":
            self.scene, self.cam = hp.GaussianScene.from_ply(DATA / "scenes" / "donut.ply"), hp.Camera.from_fov(
                320, 240, 50.0)
        else:
            self.scene, self.cam, self.fixed, self.bg = _dataset(name)
        self._cache: dict[int, tuple] = {}

    def view(self, k: int):
        if self.fixed is not None:
            return self.fixed[k]
        if k not in self._cache:
            self._cache[k] = self._synthetic(k)
        return self._cache[k]

    def rendered(self, k: int):
        """(true pose, the reference renderer's image [H, W, 3] float32 before any degradation, median depth, the
        view's random stream after drawing the pose) of synthetic view ``k``."""
        from hgsloc_plugin.refine.plan import median_depth
        from tests.reference.render_torch import render_reference

        rng = np.random.default_rng([SEED, SCENES.index(self.name), k])
        gt = _random_view(self.name, rng)
        rgb, _ = render_reference(self.scene, self.cam, gt, self.bg)
        return gt, np.asarray(rgb, np.float32), median_depth(self.scene, self.cam, gt), rng

    def _synthetic(self, k: int):
        from hgsloc_plugin.cli.demo.queries import degrade

        gt, rgb, depth, rng = self.rendered(k)
        return gt, degrade(rgb, rng, **PHOTO_DEGRADATION), depth


def _random_view(name: str, rng: np.random.Generator):
    """A random true pose of a synthetic scene."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.scene import HALF

    if name == "donut":
        az, el, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.38)
        eye = r * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        return hp.Pose.look_at(eye, [0.0, 0.0, 0.03] + rng.normal(scale=0.01, size=3))
    eye = np.array([rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(1.1, 1.7)])
    up = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 1.0])
    if name == "stripes":  # a point on the striped wall (y = +HALF), away from the corners
        target = np.array([rng.uniform(-0.6, 0.6) * HALF, HALF, rng.uniform(0.6, 1.9)])
    else:
        yaw = rng.uniform(0, 2 * np.pi)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.35, 0.1)])
    return hp.Pose.look_at(eye, target, up)


def _dataset(name: str):
    """(scene, camera, [(true pose, image, median depth)], background) of a ../shared/data set."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.core.image import load_image
    from hgsloc_plugin.refine.plan import median_depth

    folder, ply = {"snow": ("snow", "snow.ply"), "snow_sharp": ("snow", "snow_sharp.ply"),
                   "lego": ("lego", "lego.ply")}[name]
    d = DATA / folder
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(d / ply)
    white = name == "lego"
    bg = (1.0, 1.0, 1.0) if white else (0.0, 0.0, 0.0)
    views = []
    for line in (d / "gt.txt").read_text().splitlines():
        t = line.split()
        gt = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
        img = load_image(d / "queries" / t[0], background=bg)
        views.append((gt, img, median_depth(scene, cam, gt)))
    return scene, cam, views, bg


def available(scene: str) -> Path | None:
    """The file a scene needs when it is missing, else None."""
    need = {"donut": DATA / "scenes" / "donut.ply", "lego": DATA / "lego" / "lego.ply",
            "snow": DATA / "snow" / "snow.ply", "snow_sharp": DATA / "snow" / "snow_sharp.ply"}.get(scene)
    return need if need is not None and not need.exists() else None


def measured_floors(views: Views, refiner) -> MapFloor:
    """The map's floor (``evaluation.floor``) of a scene, measured on its first ``FLOOR_VIEWS`` views (a fixed
    scene's every view) refined from their true poses; a trial at one of them takes the floor without it
    (``MapFloor.without``): no trial's own view tells its floor."""
    from hgsloc_plugin.evaluation.floor import map_floor

    n = len(views.fixed) if views.fixed is not None else FLOOR_VIEWS
    measured = []
    for k in range(n):
        gt, img, _ = views.view(k)
        measured.append((img, views.cam, gt, str(k)))
    return map_floor(refiner, measured)


def run_trials(trials: list[Trial], preset: str, out_path: Path, progress: bool = True,
               map_floor: str = "default") -> None:
    """Refine each trial, appending one JSON line per trial to ``out_path``; ``map_floor`` "measured": each scene's
    trials declare the map's floor measured on its other views (:func:`measured_floors`), "measured-all": on all
    its views, the trial's own among them (as training views cover a query's part of the map: a bound, not a
    held-out figure), "default": none."""
    import hgsloc_plugin as hp
    from adapters.confidence import HLOC_FEW_INLIERS, hloc_trust, inlier_trust

    hp.init()
    if "HGSLOC_CPU_THREADS" in os.environ:  # the reference renderer's torch too: its share of the cores, no more
        import torch

        torch.set_num_threads(int(os.environ["HGSLOC_CPU_THREADS"]))
    views: dict[str, Views] = {}
    refiners: dict[str, hp.HGSLocPlugin] = {}
    floors: dict[str, MapFloor] = {}
    floor_refiners: dict[tuple, hp.HGSLocPlugin] = {}  # (scene, floor) -> its refiner
    errors: dict[str, tuple] = {}
    config = hp.RefineConfig.preset(preset)
    t_start = time.time()
    with open(out_path, "a") as f:
        for i, tr in enumerate(trials):
            if tr.scene not in views:
                views[tr.scene] = Views(tr.scene)
                refiners[tr.scene] = hp.HGSLocPlugin(views[tr.scene].scene,
                                                     config.replace(background=views[tr.scene].bg))
                if map_floor != "default":
                    floors[tr.scene] = measured_floors(views[tr.scene], refiners[tr.scene])
            if tr.localizer not in errors:
                errors[tr.localizer] = localizer_errors(tr.localizer)
            v = views[tr.scene]
            gt, img, depth = v.view(tr.view)
            errs, counts = errors[tr.localizer]
            err = errs[tr.error]
            prior = hp.Pose(err.qvec, err.tvec * depth / REFERENCE_DEPTH) @ gt
            settings = {}
            inliers = None if counts is None else counts[tr.error]
            if inliers is not None:
                settings = inlier_trust(inliers).as_dict()
            elif tr.localizer == "hloc":
                settings = hloc_trust(HLOC_FEW_INLIERS).as_dict()
            refiner, floor = refiners[tr.scene], None
            if map_floor != "default":
                floor = floors[tr.scene] if map_floor == "measured-all" else floors[tr.scene].without(str(tr.view))
                key = (tr.scene, floor.depth, floor.deg)
                if key not in floor_refiners:
                    base = refiners[tr.scene]
                    floor_refiners[key] = hp.HGSLocPlugin(base.scene, base.config.replace(**floor.tuning()),
                                                          renderer=base.renderer)
                refiner = floor_refiners[key]
            cm = 100.0 * REFERENCE_DEPTH / depth  # cm-eq per scene unit
            judged: list = []  # each route's candidate as the rule judged it: route, cm-eq, deg, refusal reason
            refiner.on_judged = _judged_into(judged, gt, cm)
            r = refiner.refine(img, v.cam, prior, name=f"{tr.scene}-{tr.view}", **settings)
            refiner.on_judged = None
            t0, r0 = prior.errors_to(gt)
            t1, r1 = r.pose.errors_to(gt)
            rec = {"index": tr.index, "scene": tr.scene, "view": tr.view, "localizer": tr.localizer,
                   "error": tr.error, "inliers": inliers, "t0": t0 * cm, "r0": r0, "t1": t1 * cm, "r1": r1,
                   "ts": r.search_pose.errors_to(gt)[0] * cm, "rs": r.search_pose.errors_to(gt)[1],
                   "accepted": bool(r.accepted), "moved": bool(r.accepted), "fused": bool(r.fused),
                   "route": r.route, "rejected": r.rejected, "confidence": float(r.confidence),
                   "sigma_t": float(r.sigma_t) * cm, "sigma_r": float(r.sigma_r_deg),
                   "renders": int(r.renders), "seconds": float(r.seconds),
                   "cost_initial": float(r.cost_initial), "cost_final": float(r.cost_final),
                   "gradient_rejected": r.gradient_rejected, "judged": judged,
                   "map_floor": None if floor is None else [floor.depth, floor.deg, floor.cost_bound],
                   "assessment": None if r.assessment is None else r.assessment.to_dict()}
            f.write(json.dumps(rec) + "\n")
            f.flush()
            if progress and (i + 1) % 10 == 0:
                print(f"  {i + 1} / {len(trials)} trials, {time.time() - t_start:.0f} s", file=sys.stderr, flush=True)


def _judged_into(out: list, gt, cm: float):
    """A ``Refiner.on_judged`` hook appending [route, centre error cm-eq, rotation error deg, refusal reason or
    None] of each judged candidate to ``out`` (``cm``: cm-eq per scene unit)."""
    def hook(cand, verdict, plan) -> None:
        t, r = cand.pose.errors_to(gt)
        out.append([cand.route, round(t * cm, 4), round(r, 4), verdict.rejected])
    return hook


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-cell", type=int, default=100, help="trials per localizer x scene")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--localizers", nargs="+", default=list(LOCALIZERS), choices=LOCALIZERS)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--map-floor", default="default", choices=("default", "measured", "measured-all"),
                    help="measured: each trial declares its map's floor and cost bound measured on the scene's "
                         "other views (hgsloc check --measure-floor's flag); measured-all: on all of them, its own "
                         "included "
                         "(a bound: training views cover the query's part of the map); default: the package's "
                         "default floor")
    ap.add_argument("--jobs", type=int, default=2, help="processes, each on its share of the cores")
    ap.add_argument("--raw", default=None, help="keep one JSON line per trial here (default: a temporary file)")
    ap.add_argument("--out", default=None, help="write the table as Markdown here")
    ap.add_argument("--from-raw", default=None, help="tabulate this raw file instead of running trials")
    ap.add_argument("--compare", default=None, help="a raw file of another run: compare trial by trial")
    ap.add_argument("--sigma-scale", type=float, default=1.0,
                    help="with --from-raw: every returned sigma times this in the within-sigma columns (what one "
                         "scale for all queries would do to the calibration)")
    ap.add_argument("--shard", default=None, help=argparse.SUPPRESS)  # "k/n": run every n-th trial from k
    args = ap.parse_args()
    if args.from_raw:
        rows = [json.loads(line) for line in Path(args.from_raw).read_text().splitlines()]
        for r in rows:
            r["sigma_t"], r["sigma_r"] = r["sigma_t"] * args.sigma_scale, r["sigma_r"] * args.sigma_scale
        report(rows, [s for s in SCENES if any(r["scene"] == s for r in rows)],
               [x for x in LOCALIZERS if any(r["localizer"] == x for r in rows)], args,
               f"{len(rows)} trials from {args.from_raw}")
        return
    if not (DATA / "poses" / "7scenes").exists():
        sys.exit(f"trials: {DATA / 'poses' / '7scenes'} not found (the localizer errors)")
    scenes = [s for s in args.scenes if available(s) is None]
    for s in set(args.scenes) - set(scenes):
        print(f"skipping {s}: {available(s)} not found", file=sys.stderr)
    sizes = {"snow": 6, "snow_sharp": 6, "lego": None}
    n_views = {s: None for s in scenes}
    for s in scenes:
        if s in sizes:
            n_views[s] = len(Views(s).fixed)
    n_errors = {loc: 17000 for loc in args.localizers}
    trials = plan_trials(scenes, args.localizers, args.per_cell, n_errors, n_views)
    raw = Path(args.raw) if args.raw else Path(os.environ.get("TMPDIR", "/tmp")) / f"trials-{os.getpid()}.jsonl"
    if args.shard:
        k, n = (int(x) for x in args.shard.split("/"))
        run_trials([t for t in trials if t.view % n == k], args.preset, raw, progress=k == 0,  # a view: one process
                   map_floor=args.map_floor)
        return
    t0 = time.time()
    parts = [raw.with_suffix(f".part{k}") for k in range(args.jobs)]
    for p in parts:
        p.unlink(missing_ok=True)
    env = dict(os.environ)  # each process its share of the cores, unless HGSLOC_CPU_THREADS says otherwise
    env.setdefault("HGSLOC_CPU_THREADS", str(max(1, (os.cpu_count() or 1) // args.jobs)))
    cmd = [*module_command(__file__), "--per-cell", str(args.per_cell), "--preset", args.preset, "--scenes", *scenes,
           "--localizers", *args.localizers, "--map-floor", args.map_floor]
    procs = [subprocess.Popen(cmd + ["--raw", str(p), "--shard", f"{k}/{args.jobs}"], env=env, cwd=ROOT)
             for k, p in enumerate(parts)]
    codes = [p.wait() for p in procs]
    if any(codes):
        sys.exit(f"trials: a worker failed (exit codes {codes})")
    rows = sorted((json.loads(line) for p in parts for line in p.read_text().splitlines()), key=lambda r: r["index"])
    raw.write_text("".join(json.dumps(r) + "\n" for r in rows))
    for p in parts:
        p.unlink()
    seconds = time.time() - t0
    report(rows, scenes, args.localizers, args,
           f"{len(rows)} trials, preset {args.preset}, {args.jobs} processes, {seconds:.0f} s wall; raw: {raw}")


def report(rows: list[dict], scenes, localizers, args, title: str) -> None:
    """Print the table (and the comparison with ``--compare``'s run) and write it to ``--out``."""
    lines = [title, ""] + table(rows, scenes, localizers)
    if args.compare:
        before = [json.loads(line) for line in Path(args.compare).read_text().splitlines()]
        lines += ["", f"Trial by trial against {args.compare}:", ""] + compare(before, rows, scenes)
    print("\n".join(lines))
    if args.out:
        from benchmarks.harness import regenerate_line, write_keeping_notes

        head = ["# Trials: the real 7-Scenes localizer errors on many views", "", regenerate_line(__file__), "",
                PAGE_INTRO, ""]
        write_keeping_notes(Path(args.out), head + lines)


if __name__ == "__main__":
    main()
