"""Rule model: does the polish's Gauss-Newton model pick the one-pixel moves the acceptance rule needs?

Usage: python -m benchmarks.rule_model [--cases snow_sharp snow lego room] [--noise 0,1,2,4,8] [--out FILE]

The rule (``refine/trust.py``) renders 6 of a polished candidate's 12 one-pixel moves: the pair the model of the
last polish stage predicts to rise least, and the four it ranks 5th to 8th (kappa: their median); all 12 when the
rendered rises do not follow the model (``model_agrees``). Here the 12 of every judged candidate are rendered
beside the refinement (read through the refiner's ``on_judged`` hook; the refinement runs as it does by default),
so the rule's inputs from the 6 can be compared with the 12: per case, the candidates judged
(every route of every query, priors of each ``--noise`` % of the median depth and half as many degrees, 0 = the
true pose), the median and lowest correlation of the model with the 12 rendered rises, how often the true minimum
is one of the flattest pair, kappa from the middle four against the median of the 12 (largest relative
difference, over the candidates whose rises follow the model), sharpness (lowest rise / kappa) flipping across
``MIN_SHARPNESS``, and the candidates whose rises do not follow the model (rendered twice: 6, then the other 6).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import hgsloc_plugin as hp
from benchmarks.harness import load
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine import trust


def record(case: str, noise: list[float]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(rendered rises [12], the model's predicted rises [12]) of every polished candidate judged in ``case``: read
    from the refiner's ``on_judged`` trace hook; the 12 one-pixel moves rendered here, at the judging size, by a
    scorer of this benchmark's own on the refinement's renderer (the refinement itself runs unchanged)."""
    from hgsloc_plugin.refine.scorer import Scorer

    cam, scene, qs, bg = load(case)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg))
    image = [None]

    def judged(cand, verdict, plan):
        cam_judge = plan.cam_polish  # the default routes polish: the rule judges at the polish's size
        moves = trust.pixel_moves(cand.pose, plan, cam_judge, refiner.config.tuning.pivot)
        predicted = trust.predicted_rises(cand, moves, cam_judge)
        if predicted is None:
            return
        scorer = Scorer(refiner.renderer_for(plan), "cs", bg, refiner.config.tuning.mask_alpha)
        scorer.set_query(cam_judge, image[0])
        costs = scorer([cand.pose, *moves])
        out.append((costs[1:] - costs[0], predicted))

    refiner.on_judged = judged
    rng = np.random.default_rng(11)
    for pct in noise:
        for _, g, img, d in qs:
            prior = se3_noise(g, pct / 2, pct / 100 * d, rng) if pct else g
            image[0] = img
            refiner.refine(img, cam, prior)
    return out


def row(case: str, recs: list[tuple[np.ndarray, np.ndarray]]) -> str:
    corr, flattest, kappa_err, flips, off = [], 0, [], 0, 0
    for rises, pred in recs:
        picked = trust.picked_moves(pred)
        corr.append(float(np.corrcoef(rises, pred)[0, 1]))
        flattest += int(np.argmin(rises) in picked[:2])
        if not trust.model_agrees(rises[picked], pred[picked]):
            off += 1
            continue
        kappa, kappa6 = np.median(rises), np.median(rises[picked[2:]])
        kappa_err.append(abs(kappa6 / kappa - 1.0))
        sharp, sharp6 = rises.min() / kappa, rises[picked].min() / kappa6
        flips += int((sharp >= trust.MIN_SHARPNESS) != (sharp6 >= trust.MIN_SHARPNESS))
    n = len(recs)
    return (f"| {case} | {n} | {np.median(corr):.3f} / {min(corr):.3f} | {flattest} / {n} | "
            f"{max(kappa_err, default=0.0):.3g} | {flips} | {off} / {n} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["snow_sharp", "snow", "lego", "room"])
    ap.add_argument("--noise", default="0,1,2,4,8", help="prior sizes, %% of the median depth (degrees: half)")
    ap.add_argument("--out", type=Path, help="also write the table as Markdown here")
    args = ap.parse_args()
    noise = [float(x) for x in args.noise.split(",")]
    lines = ["# Rule model (`benchmarks/rule_model.py`)", "",
             "Regenerate: `python -m benchmarks.rule_model --out benchmarks/rule_model.md`.", "",
             f"Priors {', '.join(f'{x:g} %' for x in noise)} of the median depth (half as many degrees); every "
             "polished candidate judged, its 12 one-pixel moves rendered.", "",
             "| case | candidates | correlation, median / lowest | true minimum in the flattest pair | "
             "kappa from 4, largest relative difference | sharpness verdict flips | rises off the model |",
             "|---|---|---|---|---|---|---|"]
    print("\n".join(lines[-2:]), flush=True)
    for case in args.cases:
        lines.append(row(case, record(case, noise)))
        print(lines[-1], flush=True)
    if args.out:
        from benchmarks.harness import write_keeping_notes

        write_keeping_notes(args.out, lines)


if __name__ == "__main__":
    main()
