"""Basin: how far a prior may be from the truth and still be refined, per scene, with the default refiner.

Usage: python -m benchmarks.basin [--cases snow_sharp snow lego room donut] [--queries 6] [--wide 16,8]
                                  [--rows ROW ...] [--out FILE]
       python -m benchmarks.basin --agreement [--cases ...] [--rows ...]
       python -m benchmarks.basin --routes [--out FILE]

One run. Real photos first: the 6 snow photos on the good map (``snow_sharp.ply``) and on the imperfect one
(``snow.ply``), then lego's held-out renders, the demo room and the donut (photo-degraded renders). Lengths are in
cm-eq, 7-Scenes-equivalent centimetres (the query's median depth scaled to 2 m; the room is metric: cm).

Rows: priors of exactly a cm-eq and b degrees in random directions, from 1 cm-eq / 0.5 deg to 60 cm-eq / 15 deg,
then priors shaped like the real DFNet and Marepo 7-Scenes outputs (their camera-frame errors against the SfM
pseudo ground truth, ``../shared/data/poses/7scenes``, one drawn per query, translation scaled to the query's
depth), and DFNet's tail (query k of n gets the error at the k-th of n quantiles of the translation from the median
to the 95th percentile). Columns: the share within 1 cm-eq / 0.5 deg, within 2 cm-eq / 0.5 deg (1 % of the
depth) and within 5 cm-eq / 5 deg before and after, queries ending worse than their prior (any amount), queries
that searched (the usual or the wide search), renders per query, seconds per query.

``--routes``: also a table of where each query whose gradient route was refused went next (the usual search
accepted, the wide search accepted or refused, no wide search), per refusal reason.

``--agreement``: every query whose usual search is refused, with the wide search run whatever the routes found
(``same_minimum_pixels=0``): the gradient route's and the search's refusal reasons, how far apart their poses are
(image motion at the final size), and what the wide search returned (the evidence for
``Tuning.same_minimum_pixels``). Default rows: 1, 15, 30, 40, 60 cm-eq and DFNet's tail.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import DATA, localizer_errors, shaped_prior, worse_count, write_keeping_notes
from benchmarks.trust import data_case, donut_case, room_case
from hgsloc_plugin.evaluation.noise import se3_noise

SIZES = ((1.0, 0.5), (5.0, 2.0), (15.0, 5.0), (30.0, 8.0), (40.0, 10.0), (60.0, 15.0))
SHAPED = (("dfnet", "DFNet-shaped"), ("marepo", "Marepo-shaped"))
TAIL = "DFNet 50th-95th pct"
CASES = {
    "snow_sharp": lambda n: data_case("snow_sharp", "snow photos, good map (snow_sharp.ply)", n),
    "snow": lambda n: data_case("snow", "snow photos, imperfect map (snow.ply)", n),
    "lego": lambda n: data_case("lego", "lego held-out renders", n),
    "room": room_case,
    "donut": donut_case,
}


def priors(gts, scale) -> dict[str, list[hp.Pose]]:
    """row -> one prior per query; ``scale`` [n]: cm-eq per scene unit of each query."""
    out = {}
    for cm, deg in SIZES:
        rng = np.random.default_rng(int(10 * cm + deg))
        out[f"{cm:g} cm-eq / {deg:g} deg"] = [se3_noise(g, deg, cm / s, rng) for g, s in zip(gts, scale)]
    if (DATA / "poses" / "7scenes").exists():
        for method, label in SHAPED:
            errs = localizer_errors(method)
            rng = np.random.default_rng(500)
            out[label] = [shaped_prior(g, errs[int(rng.integers(len(errs)))], 200.0 / s) for g, s in zip(gts, scale)]
        # DFNet's tail: query k gets the error at the k-th of n quantiles from the median to the 95th percentile of
        # the translation (camera-frame error, as the issue measured it)
        errs = sorted(localizer_errors("dfnet"), key=lambda e: float(np.linalg.norm(e.tvec)))
        qs = np.linspace(50, 95, len(gts))
        out[TAIL] = [shaped_prior(g, errs[min(int(q / 100 * len(errs)), len(errs) - 1)], 200.0 / s)
                     for g, s, q in zip(gts, scale, qs)]
    return out


def within(e: np.ndarray, cm: float, deg: float) -> float:
    return 100.0 * float(np.mean((e[:, 0] <= cm + 1e-6) & (e[:, 1] <= deg + 1e-6)))  # exact-size priors count


@contextlib.contextmanager
def route_verdicts(refiner):
    """While inside, each judged route of ``refiner``'s refinements is appended to the yielded list as (route
    name, pose, refusal reason or None, plan), through its trace hook (``Refiner.on_judged``)."""
    routes: list = []
    refiner.on_judged = lambda cand, verdict, plan: routes.append((cand.route, cand.pose, verdict.rejected, plan))
    try:
        yield routes
    finally:
        refiner.on_judged = None


def outcome(routes: list) -> tuple[str, str] | None:
    """(the gradient route's refusal, where the query went next) from one refinement's ``route_verdicts``; None
    when the gradient route was accepted or did not run."""
    if not routes or routes[0][0] != "gradient" or routes[0][2] is None:
        return None
    verdict = {name: why for name, _, why, _ in routes}
    if "search" not in verdict:
        return routes[0][2], "no search"
    if verdict["search"] is None:
        return routes[0][2], "usual search accepted"
    if "wide search" not in verdict:
        return routes[0][2], "no wide search"
    return routes[0][2], "wide search " + ("accepted" if verdict["wide search"] is None else "refused")


OUTCOMES = ("usual search accepted", "wide search accepted", "wide search refused", "no wide search", "no search")


def outcome_table(counts: dict) -> list[str]:
    """Markdown (``--routes``): per refusal reason of the gradient route, where its queries went."""
    lines = ["", "Where each refused gradient route went (`--routes`):", "",
             "| gradient route refused as | " + " | ".join(OUTCOMES) + " |", "|---" * (len(OUTCOMES) + 1) + "|"]
    for why in sorted({w for w, _ in counts}, key=lambda w: -sum(v for (x, _), v in counts.items() if x == w)):
        total = sum(v for (x, _), v in counts.items() if x == why)
        lines.append(f"| {why} ({total}) | " + " | ".join(str(counts.get((why, o), 0)) for o in OUTCOMES) + " |")
    return lines


def run(name: str, n: int, config: hp.RefineConfig, rows: list[str] | None = None,
        outcomes: dict | None = None) -> list[str]:
    """Markdown table of case ``name``; ``outcomes``: counts of (gradient refusal, next step) are added there."""
    case = CASES[name](n)
    if case is None:
        return []
    label, scene, cam, gts, imgs, scale, bg = case
    refiner = hp.HGSLocPlugin(scene, config.replace(background=bg))
    lines = [f"\n### {label}: {len(gts)} queries, {scene.num_gaussians:,} Gaussians\n",
             "| prior | prior median t / R | within 1 cm-eq / 0.5 deg before -> after (%) | within 2 cm-eq / 0.5 deg "
             "before -> after (%) | within 5 cm-eq / 5 deg before -> after (%) | worse | searched | renders / query "
             "| s / query |",
             "|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for row, ps in priors(gts, scale).items():
        if rows and row not in rows:
            continue
        e0, e1, ren, searched = [], [], [], 0
        t0 = time.perf_counter()
        for g, img, p, s in zip(gts, imgs, ps, scale):
            with route_verdicts(refiner) as routes:
                r = refiner.refine(img, cam, p)
            went = outcome(routes)
            if outcomes is not None and went is not None:
                outcomes[went] = outcomes.get(went, 0) + 1
            for lst, pose in ((e0, p), (e1, r.pose)):
                t, a = pose.errors_to(g)
                lst.append((t * s, a))
            ren.append(r.renders)
            searched += r.route != "gradient"
        sec = (time.perf_counter() - t0) / len(gts)
        e0, e1 = np.array(e0), np.array(e1)
        worse = worse_count(e0, e1)
        line = (f"| {row} | {np.median(e0[:, 0]):.1f} / {np.median(e0[:, 1]):.2f} | "
                f"{within(e0, 1, 0.5):.0f} -> {within(e1, 1, 0.5):.0f} | {within(e0, 2, 0.5):.0f} -> "
                f"{within(e1, 2, 0.5):.0f} | {within(e0, 5, 5):.0f} -> "
                f"{within(e1, 5, 5):.0f} | {worse} / {len(gts)} | {searched} | {np.mean(ren):.0f} | {sec:.1f} |")
        print(line, flush=True)
        lines.append(line)
    return lines


def agreement(name: str, n: int, rows: list[str] | None) -> list[str]:
    """Markdown rows (``--agreement``) of the queries of case ``name`` that reached the wide search."""
    case = CASES[name](n)
    if case is None:
        return []
    _, scene, cam, gts, imgs, scale, bg = case
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig.preset("default", background=bg, same_minimum_pixels=0.0))
    lines = []
    for row, ps in priors(gts, scale).items():
        if row not in (rows or AGREEMENT_ROWS):
            continue
        for k, (g, img, p, s) in enumerate(zip(gts, imgs, ps, scale)):
            with route_verdicts(refiner) as routes:
                r = refiner.refine(img, cam, p)
            if len(routes) < 3:
                continue
            (_, pg, why_g, plan), (_, ps_, why_s, _) = routes[0], routes[1]
            px = plan.pixels_apart(pg, ps_)
            t, a = r.pose.errors_to(g)
            line = (f"| {name} | {row} | {k} | {why_g} | {why_s} | {px:.2f} | "
                    f"{'accepted' if r.accepted else routes[2][2]} | {t * s:.2f} / {a:.2f} | {r.renders} |")
            print(line, flush=True)
            lines.append(line)
    return lines


AGREEMENT_ROWS = ("1 cm-eq / 0.5 deg", "15 cm-eq / 5 deg", "30 cm-eq / 8 deg", "40 cm-eq / 10 deg",
                  "60 cm-eq / 15 deg", TAIL)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    ap.add_argument("--queries", type=int, default=6)
    ap.add_argument("--wide", help="Tuning.wide_step_pixels, e.g. 16,8, or 'off' (default: the default "
                                   "config's)")
    ap.add_argument("--rows", nargs="+", help="only these rows (e.g. '30 cm-eq / 8 deg')")
    ap.add_argument("--out", type=Path, help="also write the tables as Markdown here")
    ap.add_argument("--agreement", action="store_true", help="only the routes' agreement before a wide search")
    ap.add_argument("--routes", action="store_true", help="also tabulate where each refused gradient route went")
    a = ap.parse_args()
    if a.agreement:
        print("| case | prior | query | gradient route | search | apart (px) | wide search | after (cm-eq / deg) "
              "| renders |\n|---|---|---|---|---|---|---|---|---|", flush=True)
        for c in a.cases:
            agreement(c, a.queries, a.rows)
        return
    wide = () if a.wide == "off" else tuple(float(x) for x in a.wide.split(",")) if a.wide else None
    config = hp.RefineConfig.preset("default", **({"wide_step_pixels": wide} if wide is not None else {}))
    arch = hp.init()
    t0 = time.perf_counter()
    lines, outcomes = [], {}
    for c in a.cases:
        lines += run(c, a.queries, config, a.rows, outcomes)
    if a.routes:
        lines += outcome_table(outcomes)
        print("\n".join(outcome_table(outcomes)), flush=True)
    if a.out:
        head = ["# Basin (`benchmarks/basin.py`)", "",
                f"Regenerate: `python -m benchmarks.basin --out {a.out}`. Backend {arch}; "
                f"{'wide_step_pixels ' + a.wide if a.wide else 'default config'}; one run, "
                f"{(time.perf_counter() - t0) / 60:.0f} min. cm-eq: 7-Scenes-equivalent cm (the room: cm)."]
        write_keeping_notes(a.out, head + lines)


if __name__ == "__main__":
    main()
