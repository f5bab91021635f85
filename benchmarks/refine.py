"""Refinement modes side by side: search only, search + polish, gradient only, gradient first (default), paper.

Usage: python -m benchmarks.refine [--queries 6] [--paper-queries 2] [--lego-queries 6] [--modes M ...] [--cases C ...]
       [--out benchmarks/refine.md]

Same queries and priors for every mode, one run. Cases, real photographs first:
- ``snow``: 6 real phone photos against a 3DGS fitted to other photos (an imperfect map; ../shared/data/snow);
  errors in 7-Scenes-equivalent cm (% of the query's median depth x 2) and degrees.
- ``lego``: held-out renders whose pixels no 3DGS made (../shared/data/lego); 7-Scenes-equivalent cm too.
- the demo room, photo-degraded renderings at 320x240; cm.
Rows: median (worst) error of the prior and of the returned pose, queries made worse (> 1 cm or > 0.5 deg),
accepted, lattice renders, derivative passes, render-equivalents (renders + passes x the measured cost of a
pass in renders: one pose of a 12-pose scoring batch at the search's final size, same run), seconds per query.
``candidate``: the search's (+ polish's) pose before the acceptance rule. ``truth`` rows start at the true
pose: their candidate is where each map's own cost minimum lies (its floor).
A final sweep measures where gradient only stops converging (room; converged = < 1 cm and < 0.5 deg).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import (
    DATA,
    ROOT,
    load_dataset,
    localizer_errors,
    regenerate_line,
    shaped_prior,
    write_keeping_notes,
)
from hgsloc_plugin.cli.demo.queries import degrade, query_poses
from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
from hgsloc_plugin.cli.demo.scene import make_room_scene
from hgsloc_plugin.core.image import resize_image
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.render import get_renderer

MODES = {
    "search only": hp.RefineConfig(routes="lattice"),
    "search + polish": hp.RefineConfig.preset("search"),
    "gradient only": hp.RefineConfig.preset("gradient"),
    "gradient first, then search (default)": hp.RefineConfig(),
}
NOISE = ((1.0, 0.5), (3.0, 1.0), (10.0, 3.0))
SWEEP = ((1.0, 0.5), (3.0, 1.0), (5.0, 2.0), (10.0, 3.0), (20.0, 5.0), (30.0, 10.0))


class PassCost:
    """Measured cost of a derivative pass in renders, per image size, for one scene (timed in this run)."""

    def __init__(self, scene, cam: hp.Camera, pose: hp.Pose, img: np.ndarray, config: hp.RefineConfig):
        self.r = get_renderer(scene)
        self.cam, self.pose, self.img, self.bg = cam, pose, img, config.background
        final = cam.with_max_side(config.score_max_side)
        q = self.r.upload_window_query(resize_image(img, final.width, final.height))
        poses = [pose.perturbed_in_camera([1e-4 * k, 0, 0], [0, 0, 0]) for k in range(12)]
        self.r.window_cost(final, poses, q, self.bg)
        self.t_render = min(self._time(lambda: self.r.window_cost(final, poses, q, self.bg)) for _ in range(3)) / 12
        self.ratio: dict[tuple[int, int], float] = {}

    @staticmethod
    def _time(fn) -> float:
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    def of(self, width: int, height: int) -> float:
        key = (width, height)
        if key not in self.ratio:
            cam = self.cam.with_max_side(max(width, height))
            q = self.r.upload_window_query(resize_image(self.img, cam.width, cam.height))
            self.r.pose_gradient(cam, [self.pose], q, self.bg)
            t = min(self._time(lambda: self.r.pose_gradient(cam, [self.pose], q, self.bg)) for _ in range(3))
            self.ratio[key] = t / self.t_render
        return self.ratio[key]

    def render_equivalents(self, result) -> float:
        return result.renders + sum(p.passes * self.of(p.width, p.height) for p in result.polish)


def evaluate(refiner, cam, gts, imgs, priors, scale, cost: PassCost) -> dict:
    e0, e1, es, ren, passes, req, sec, acc = [], [], [], [], [], [], [], 0
    for k, (img, gt, prior) in enumerate(zip(imgs, gts, priors)):
        r = refiner.refine(img, cam, prior)
        for lst, p in ((e0, prior), (e1, r.pose), (es, r.search_pose)):
            t, a = p.errors_to(gt)
            lst.append((t * scale[k], a))
        ren.append(r.renders)
        passes.append(r.derivative_passes)
        req.append(cost.render_equivalents(r))
        sec.append(r.seconds)
        acc += r.accepted
    e0, e1, es = np.array(e0), np.array(e1), np.array(es)
    worse = int(((e1[:, 0] > e0[:, 0] + 1.0) | (e1[:, 1] > e0[:, 1] + 0.5)).sum())
    return dict(e0=e0, e1=e1, es=es, worse=worse, acc=acc, n=len(gts), renders=np.median(ren), passes=np.median(passes),
                req=np.median(req), sec=np.median(sec))


def fmt(e: np.ndarray) -> str:
    return f"{np.median(e[:, 0]):.2f} / {np.median(e[:, 1]):.3f} ({e[:, 0].max():.2f} / {e[:, 1].max():.2f})"


def row(mode: str, prior: str, m: dict) -> str:
    return (f"| {mode} | {prior} | {fmt(m['e0'])} | {fmt(m['es'])} | {fmt(m['e1'])} | {m['worse']} | "
            f"{m['acc']} / {m['n']} | {m['renders']:.0f} | {m['passes']:.0f} | {m['req']:.0f} | {m['sec']:.2f} |")


HEADER = ["| mode | prior | prior median (worst) t / R | candidate | returned median (worst) | worse | accepted | "
          "renders | derivative passes | render-equivalents | s / query |", "|" + "---|" * 11]


def priors_for(gts, scale, seed=0) -> dict:
    out = {"truth (map floor)": list(gts)}
    for cm, deg in NOISE:
        rng = np.random.default_rng(int(10 * cm + deg) + seed)
        out[f"{cm:g} cm / {deg:g} deg"] = [se3_noise(g, deg, cm / s, rng) for g, s in zip(gts, scale)]
    if (DATA / "poses" / "7scenes").exists():
        errs = localizer_errors("marepo")
        rng = np.random.default_rng(300)
        out["Marepo-shaped"] = [shaped_prior(g, errs[int(rng.integers(len(errs)))], 200.0 / s)
                                for g, s in zip(gts, scale)]
    return out


def run_case(label, scene, cam, gts, imgs, scale, bg, lines, modes) -> None:
    lines += [f"\n### {label}: {len(gts)} queries, {scene.num_gaussians} Gaussians\n"] + HEADER
    print("\n".join(lines[-3:]), flush=True)
    cost = PassCost(scene, cam, gts[0], imgs[0], hp.RefineConfig(background=bg))
    for mode, cfg in modes.items():
        refiner = hp.HGSLocPlugin(scene, cfg.replace(background=bg))
        for name, ps in priors_for(gts, scale).items():
            lines.append(row(mode, name, evaluate(refiner, cam, gts, imgs, ps, scale, cost)))
            print(lines[-1], flush=True)
    ratios = ", ".join(f"{w}x{h}: {v:.1f}" for (w, h), v in sorted(cost.ratio.items()))
    lines.append(f"\nOne derivative pass in renders (this run): {ratios}; one render = "
                 f"{1e3 * cost.t_render:.1f} ms.")
    print(lines[-1], flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--queries", type=int, default=6)
    ap.add_argument("--paper-queries", type=int, default=2)
    ap.add_argument("--lego-queries", type=int, default=6)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "refine.md"))
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES), metavar="MODE",
                    help=f"modes to run (default: all of {list(MODES)})")
    ap.add_argument("--cases", nargs="+", default=["snow", "lego", "room", "paper", "sweep"],
                    choices=["snow", "lego", "room", "paper", "sweep"])
    a = ap.parse_args()
    hp.init()
    t_start = time.time()
    lines: list[str] = []
    modes = {m: MODES[m] for m in a.modes}
    snow = load_dataset("snow") if "snow" in a.cases else None
    if snow is not None:
        cam, scene, qs, bg = snow
        qs = qs[: a.queries]
        run_case("snow (real photos; 7-Scenes-equivalent cm)", scene, cam, [q[1] for q in qs], [q[2] for q in qs],
                 [200.0 / q[3] for q in qs], bg, lines, modes)
    lego = load_dataset("lego") if "lego" in a.cases else None
    if lego is not None and a.lego_queries > 0:
        cam, scene, qs, bg = lego
        qs = qs[: a.lego_queries]
        run_case("lego (held-out renders, white background; 7-Scenes-equivalent cm)", scene, cam, [q[1] for q in qs],
                 [q[2] for q in qs], [200.0 / q[3] for q in qs], bg, lines, modes)
    scene = make_room_scene()
    cam = QUERY_CAMERA
    gts = query_poses(a.queries, seed=1)
    imgs = [degrade(im, np.random.default_rng(1000 + k)) for k, im in enumerate(hp.render(scene, cam, gts))]
    paper = hp.RefineConfig.preset("paper", paper_step_q=2e-4, paper_step_t=2e-3, score_max_side=160)
    if "room" in a.cases:
        run_case("demo room (photo-degraded renders; cm)", scene, cam, gts, imgs, [100.0] * len(gts),
                 (0.0, 0.0, 0.0), lines, modes)
    cost = PassCost(scene, cam, gts[0], imgs[0], hp.RefineConfig())
    if "paper" in a.cases:
        paper_rows(a, scene, cam, gts, imgs, paper, cost, lines)
    if "sweep" in a.cases:
        sweep_rows(scene, cam, gts, imgs, cost, lines)
    write(a.out, lines, t_start)


def paper_rows(a, scene, cam, gts, imgs, paper, cost, lines) -> None:
    lines += [f"\n### demo room, emulated official scheme ({a.paper_queries} queries)\n"] + HEADER
    refiner = hp.HGSLocPlugin(scene, paper)
    n = a.paper_queries
    for cm, deg in NOISE[:2]:
        rng = np.random.default_rng(int(10 * cm + deg))
        ps = [se3_noise(g, deg, cm / 100.0, rng) for g in gts][:n]
        lines.append(row("paper emulation", f"{cm:g} cm / {deg:g} deg",
                         evaluate(refiner, cam, gts[:n], imgs[:n], ps, [100.0] * n, cost)))
        print(lines[-1], flush=True)


def sweep_rows(scene, cam, gts, imgs, cost, lines) -> None:
    lines += ["\n### where gradient only stops converging (demo room; converged: < 1 cm and < 0.5 deg)\n",
              "| prior | gradient only: converged | median error | search + polish: converged | median error |",
              "|---|---|---|---|---|"]
    print("\n".join(lines[-3:]), flush=True)
    for cm, deg in SWEEP:
        rng = np.random.default_rng(int(10 * cm + deg) + 7)
        ps = [se3_noise(g, deg, cm / 100.0, rng) for g in gts]
        cells = []
        for mode in ("gradient only", "search + polish"):
            m = evaluate(hp.HGSLocPlugin(scene, MODES[mode]), cam, gts, imgs, ps, [100.0] * len(gts), cost)
            ok = (m["e1"][:, 0] < 1.0) & (m["e1"][:, 1] < 0.5)
            cells += [f"{ok.sum()} / {len(ok)}", f"{np.median(m['e1'][:, 0]):.2f} / {np.median(m['e1'][:, 1]):.3f}"]
        lines.append(f"| {cm:g} cm / {deg:g} deg | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)


def write(out, lines, t_start) -> None:
    text = ("# Refinement modes\n\n" + regenerate_line(__file__) + "\n\n" + __doc__.split("\n\n", 2)[2].strip() +
            f"\n\nBackend {hp.current_arch()}; total time {time.time() - t_start:.0f} s.\n" + "\n".join(lines))
    write_keeping_notes(Path(out), text.splitlines(), section="## ")  # its discussion sections kept
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
