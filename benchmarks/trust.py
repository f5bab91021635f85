"""Trust benchmark: is a returned pose ever worse than its prior, and does the confidence say which to trust?

Usage: python -m benchmarks.trust [--scenes snow_sharp snow lego room donut] [--queries 6] [--draws 3]
    [--out benchmarks/trust.md]

Scenes (real pixels first):
- ``snow_sharp`` / ``snow``: 6 real phone photos against a good 3DGS (``snow_sharp.ply``, 24.1 dB held out) and an
  imperfect one (``snow.ply``, 20.6 dB) of the same room (``../shared/data/snow``);
- ``lego``: held-out Blender renders (pixels no 3DGS made) against a 3DGS fitted to other views
  (``../shared/data/lego``; the first ``--queries`` of its 15);
- ``room``: the embedded demo room, photo-degraded renderings (``hgsloc demo``'s queries);
- ``donut``: ``../shared/data/scenes/donut.ply``, photo-degraded renderings (a small object at ~0.35 units).

Errors are in **7-Scenes-equivalent centimetres**: metres x 100 on the room (a metric scene), elsewhere the
centre error scaled by 2 m over the query's median depth (7-Scenes' typical depth), so "1 cm" means the same
image motion on every scene. Priors:
- ``truth``: the true pose itself (a good cost leaves it there; "worse" = moved > 1 cm or > 0.5 deg away);
- ``D cm / R deg``: exactly D equivalent cm and R degrees in random directions, from small to beyond the
  search's reach (1 / 0.5, 3 / 1, 10 / 3, 30 / 10);
- ``1 cm / 0.5 deg, region 2 cm / 1 deg``: the 1 cm priors with the trust region set from the localizer's
  expected error (``--max-shift`` / ``--max-rotation``, here twice it) instead of from the coarsest step;
- ``1 cm / 0.5 deg, error 1 cm / 0.5 deg declared``: the 1 cm priors with their error declared
  (``--prior-error`` / ``--prior-rotation-error``): an accepted refined pose is fused with the prior, weighted by
  the refined pose's covariance and the declared error (``refine/trust.py``, ``fuse_with_prior``);
- ``ACE-shaped`` / ``Marepo-shaped``: the camera-frame errors of the real ACE / Marepo estimates of 7-Scenes
  against the SfM pGT (``../shared/data/poses/7scenes``), one drawn per query, so heavy tails included;
- ``ACE-shaped, ACE's inliers``: the same priors, each with the inlier count ACE wrote for the estimate its
  error was drawn from, which sets the query's trust region and expected error (``adapters/confidence.py``:
  1.5x the 99th percentile and the median of ACE + GLACE errors at that count), as ``hgsloc refine`` does for
  an ACE file;
- ``Marepo-shaped, error declared``: the Marepo-shaped priors with Marepo's median 7-Scenes error declared (a
  localizer without a per-pose confidence: one figure for all its poses).

Per row: queries improved / unchanged / made worse (worse: the returned pose is > 1 cm or > 0.5 deg further from
the truth than the prior), recall at 5 cm 5 deg / 2 cm 2 deg / 1 cm 1 deg before and after, and how well the
confidence separates good from bad: median error of accepted results, median error the rejected searches
would have had, and the area under the ROC curve of the confidence for "the search pose is better than the
prior" (1 = perfect ranking, 0.5 = chance; "-" when all searches were good or all bad); and the reported
uncertainty of accepted results (``RefineResult.sigma_t`` / ``sigma_r_deg``, converted to the same units):
median sigma, and the median of |error| / sigma (about 0.9 for a calibrated 3D sigma; > 1: it understates the
error). The goal is 0 worse on every row.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import DATA, load_dataset, localizer_errors, regenerate_line, shaped_prior, write_keeping_notes
from hgsloc_plugin.adapters.confidence import inlier_trust
from hgsloc_plugin.cli.demo.queries import degrade, query_poses
from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
from hgsloc_plugin.cli.demo.scene import make_room_scene
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.plan import median_depth

LEVELS = ((1.0, 0.5), (3.0, 1.0), (10.0, 3.0), (30.0, 10.0))
WORSE_CM, WORSE_DEG = 1.0, 0.5
RECALLS = ((5.0, 5.0), (2.0, 2.0), (1.0, 1.0))
# rows with what a user declares about the priors (--max-shift / --max-rotation / --prior-error /
# --prior-rotation-error): row name -> (the priors' row, Refiner.refine keywords with lengths in equivalent cm;
# "median" = the localizer's median 7-Scenes error, measured from the files)
DECLARED = {"1 cm / 0.5 deg, region 2 cm / 1 deg": ("1 cm / 0.5 deg", {"max_shift": 2.0, "max_rotation_deg": 1.0}),
            "1 cm / 0.5 deg, error 1 cm / 0.5 deg declared": ("1 cm / 0.5 deg",
                                                             {"prior_error": 1.0, "prior_error_deg": 0.5}),
            "Marepo-shaped, error declared": ("Marepo-shaped", {"prior_error": "median", "prior_error_deg": "median"})}
LENGTHS = ("max_shift", "prior_error")
# rows whose priors carry the localizer's inlier count, which sets each query's region and expected error
# (adapters/confidence.py, what `hgsloc refine` does with ACE files): row name -> the priors' row
INLIER_ROWS = {"ACE-shaped, ACE's inliers": "ACE-shaped"}


def data_case(name: str, label: str, n: int):
    """A ../shared/data set with real pixels (snow, lego): its first n queries; None when absent."""
    loaded = load_dataset(name)
    if loaded is None:
        return None
    cam, scene, queries, bg = loaded
    queries = queries[:n]
    return (label, scene, cam, [q[1] for q in queries], [q[2] for q in queries], [200.0 / q[3] for q in queries], bg)


def snow_sharp_case(n):
    return data_case("snow_sharp", "snow, sharp map (real photos)", n)


def snow_case(n):
    return data_case("snow", "snow (real photos)", n)


def lego_case(n):
    return data_case("lego", "lego (held-out renders, real pixels)", n)


def synthetic_case(label, scene, cam, gts, metric: bool):
    imgs = [degrade(im, np.random.default_rng(1000 + k)) for k, im in enumerate(hp.render(scene, cam, gts))]
    scale = [100.0 if metric else 200.0 / median_depth(scene, cam, g) for g in gts]
    return (label, scene, cam, gts, imgs, scale, (0.0, 0.0, 0.0))


def room_case(n):
    return synthetic_case("demo room (degraded renders)", make_room_scene(), QUERY_CAMERA, query_poses(n, seed=1),
                          metric=True)


def donut_case(n):
    path = DATA / "scenes" / "donut.ply"
    if not path.exists():
        print(f"skipping donut: {path} not found", file=sys.stderr)
        return None
    rng = np.random.default_rng(0)
    gts = []
    for _ in range(n):
        az, el, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 0.9), rng.uniform(0.3, 0.38)
        eye = r * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        gts.append(hp.Pose.look_at(eye, [0.0, 0.0, 0.03] + rng.normal(scale=0.01, size=3)))
    return synthetic_case("donut (degraded renders)", hp.GaussianScene.from_ply(path),
                          hp.Camera.from_fov(320, 240, 50.0), gts, metric=False)


def priors(gts, scale, inliers: dict | None = None, draws: int = 1, medians: dict | None = None) -> dict:
    """protocol name -> priors, query k's at positions k, k + n, ...: one per query, ``draws`` per query for the
    localizer-shaped rows; ``inliers``, when given, gets protocol name -> the localizer's inlier count of each
    prior's error (localizer-shaped rows); ``medians``: protocol name -> the localizer's median error (cm, deg)."""
    out = {"truth": list(gts)}
    for cm, deg in LEVELS:
        rng = np.random.default_rng(int(10 * cm + deg))
        out[f"{cm:g} cm / {deg:g} deg"] = [se3_noise(g, deg, cm / s, rng) for g, s in zip(gts, scale)]
    if (DATA / "poses" / "7scenes").exists():
        for method, label in (("ace", "ACE-shaped"), ("marepo", "Marepo-shaped")):
            counts: list = []
            errs = localizer_errors(method, counts)
            rng = np.random.default_rng(300)
            picks = [int(rng.integers(len(errs))) for _ in range(draws) for _ in gts]
            # shaped_prior scales by depth / 2 m; here depth / 2 m = 100 / scale (scale = 200 / depth)
            out[label] = [shaped_prior(gts[j % len(gts)], errs[i], 200.0 / scale[j % len(gts)])
                          for j, i in enumerate(picks)]
            if inliers is not None:
                inliers[label] = [counts[i] for i in picks]
            if medians is not None:
                e = np.array([err.errors_to(hp.Pose.identity()) for err in errs])  # centre (m at 2 m), deg
                medians[label] = (100.0 * float(np.median(e[:, 0])), float(np.median(e[:, 1])))
    else:
        print("skipping localizer-shaped priors: ../shared/data/poses/7scenes not found", file=sys.stderr)
    return out


def auc(score: np.ndarray, good: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for the boolean ``good`` (ties count one half); nan if one class."""
    pos, neg = score[good], score[~good]
    if not len(pos) or not len(neg):
        return float("nan")
    gt = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(gt / (len(pos) * len(neg)))


def recall(e: np.ndarray) -> str:
    return "/".join(f"{100 * np.mean((e[:, 0] <= t) & (e[:, 1] <= r)):.0f}" for t, r in RECALLS)


def run_case(case, config: hp.RefineConfig, draws: int = 1) -> list[str]:
    label, scene, cam, gts, imgs, scale, bg = case
    refiner = hp.HGSLocPlugin(scene, config.replace(background=bg))
    lines = [f"\n### {label}: {len(gts)} queries ({draws} priors each in the localizer-shaped rows), "
             f"{scene.num_gaussians} Gaussians\n",
             "| prior | median before (worst) | median after (worst) | improved / unchanged / worse | "
             "recall 5/2/1 before | after | accepted | median err accepted / rejected search | AUC | "
             "sigma t / R (err / sigma) | s / q |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    counts: dict = {}
    medians: dict = {}
    rows = priors(gts, scale, counts, draws, medians)
    rows.update({name: rows[src] for name, (src, _) in DECLARED.items() if src in rows})
    rows.update({name: rows[src] for name, src in INLIER_ROWS.items() if src in rows})
    for name, ps in rows.items():
        t0 = time.perf_counter()
        e0, e1, es, conf, acc, sig = [], [], [], [], [], []
        fused = 0
        for j, prior in enumerate(ps):
            k = j % len(gts)
            img, gt = imgs[k], gts[k]
            per_query = {}
            if name in DECLARED:  # lengths in scene units for this query (scale: equivalent cm per unit)
                src, declared = DECLARED[name]
                for key, v in declared.items():
                    v = medians[src][0 if key in LENGTHS else 1] if v == "median" else v
                    per_query[key] = v / scale[k] if key in LENGTHS else v
            if name in INLIER_ROWS:  # as the pipeline sets them for a record of an ACE file
                per_query = inlier_trust(counts[INLIER_ROWS[name]][j]).as_dict()
            r = refiner.refine(img, cam, prior, name=str(k), **per_query)
            for lst, p in ((e0, prior), (e1, r.pose), (es, r.search_pose)):
                t, a = p.errors_to(gt)
                lst.append((t * scale[k], a))
            conf.append(r.confidence if r.accepted else 0.0)
            acc.append(r.accepted)
            fused += r.accepted and r.fused
            sig.append((r.sigma_t * scale[k], r.sigma_r_deg))
        sec = (time.perf_counter() - t0) / len(ps)
        e0, e1, es, conf, acc, sig = map(np.array, (e0, e1, es, conf, acc, sig))
        worse = (e1[:, 0] > e0[:, 0] + WORSE_CM) | (e1[:, 1] > e0[:, 1] + WORSE_DEG)
        better = ~worse & ((e1[:, 0] < e0[:, 0] - 1e-9) | (e1[:, 1] < e0[:, 1] - 1e-9)) & acc
        unchanged = ~worse & ~better
        search_good = (es[:, 0] <= e0[:, 0]) & (es[:, 1] <= e0[:, 1])

        def med(e, worst=True):
            if not len(e):
                return "-"
            m = f"{np.median(e[:, 0]):.2f} / {np.median(e[:, 1]):.2f}"
            return m + (f" ({e[:, 0].max():.1f} / {e[:, 1].max():.1f})" if worst else "")

        a = auc(conf, search_good)
        ok = acc & np.all(np.isfinite(sig), axis=1)
        sg = "-"
        if ok.any():
            ratio = np.median(e1[ok] / sig[ok], axis=0)
            sg = (f"{np.median(sig[ok, 0]):.2f} / {np.median(sig[ok, 1]):.2f} ({ratio[0]:.2f} / {ratio[1]:.2f})")
        row = (f"| {name} | {med(e0)} | {med(e1)} | {better.sum()} / {unchanged.sum()} / {worse.sum()} | "
               f"{recall(e0)} | {recall(e1)} | {acc.sum()} / {len(acc)}{f' ({fused} fused)' if fused else ''} | "
               f"{med(e1[acc], False)} / "
               f"{med(es[~acc], False)} | {'-' if np.isnan(a) else f'{a:.2f}'} | {sg} | {sec:.1f} |")
        print(row, flush=True)
        lines.append(row)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["snow_sharp", "snow", "lego", "room", "donut"])
    ap.add_argument("--queries", type=int, default=6, help="queries per scene (snow has 6)")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--draws", type=int, default=3, help="priors per query in the localizer-shaped rows")
    ap.add_argument("--out", default=None, help="also write the tables as Markdown here")
    args = ap.parse_args()
    hp.init()
    config = hp.RefineConfig.preset(args.preset)
    makers = {"snow_sharp": snow_sharp_case, "snow": snow_case, "lego": lego_case, "room": room_case,
              "donut": donut_case}
    t_start = time.time()
    lines = ["# Trust benchmark (`benchmarks/trust.py`)", "", regenerate_line(__file__),
             f"\nPreset {args.preset}; backend {hp.current_arch()}; errors in 7-Scenes-equivalent cm / deg; "
             f"worse = > {WORSE_CM:g} cm or > {WORSE_DEG:g} deg further from the truth than the prior."]
    for s in args.scenes:
        case = makers[s](args.queries)
        if case is not None:
            lines += run_case(case, config, args.draws)
    lines.append(f"\nTotal {time.time() - t_start:.0f} s.")
    print(lines[-1])
    if args.out:
        write_keeping_notes(Path(args.out), lines)


if __name__ == "__main__":
    main()
