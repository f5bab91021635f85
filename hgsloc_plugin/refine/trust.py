"""The acceptance rule, the pose's uncertainty and the fusion with a prior of known error.

A lower cost is not a better pose on an imperfect map, so the rule measures everything against the cost's own
scale at the candidate: the **one-pixel rise** ``kappa``, the median rise of the cost over the 12 lattice moves
of one pixel of image motion around it. The candidate is returned only when it passes every test, in order:
"no improvement" (its cost is not below the coarse pose's), "insignificant" (the drop is under
``MIN_SIGNIFICANCE`` kappa), "weak alignment" (structural costs: kappa under ``MIN_ALIGNMENT`` of the cost),
"flat valley" (some move rises less than ``MIN_SHARPNESS`` kappa), "trust-region edge" (beyond ``EDGE_FRACTION``
of the region), "level inconsistency" (the fine levels moved it more than ``MAX_LEVEL_SHIFT`` coarsest steps),
and for a polished pose without a prior of known error "within uncertainty" (the prior lies less than
``MIN_PRIOR_DISTANCE`` of the pose's own standard deviations, under the rule's band covariance, from it: not
clearly better than the prior). Where the map's cost level is declared (``Tuning.map_cost_bound``, measured on views
with known poses: ``evaluation/floor.py``), a candidate whose cost at the judging size lies above it is refused too
("cost above the map's level": right answers on this map do not end there), whatever else it passed.
A polished candidate first renders 6 of the 12 moves (``model_moves``): its last polish stage's Gauss-Newton model
ranks them, and the rule renders the pair it predicts to rise least (the flattest axis: the minimum) and the four
at the middle of the ranking (kappa: their median). When the rendered rises do not follow the model
(``model_agrees``: a rise at or below zero, or ratios to the prediction spread more than ``MODEL_SPREAD``), the
other 6 are rendered too and the rule reads all 12.

A polished pose's uncertainty, its confidence and its fusion with a prior of known error are ``uncertainty.py``'s.
Where the thresholds and factors come from: ``benchmarks/trust.md``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..core.pose import Pose, rotation_angle_deg
from .uncertainty import (
    BANDS,
    FLOOR_DEG,
    FLOOR_DEPTH,
    fuse_with_prior,
    fused_covariance,
    pixel_noise_uncertainty,
    pose_uncertainty,
    prior_distance,
    sigmas,
    within_tolerance,
)

if TYPE_CHECKING:
    from ..core.camera import Camera
    from .plan import Plan
    from .polish import PolishStats
    from .routes import Candidate
    from .scorer import Scorer

#: ``Verdict.rejected`` when the fusion with a prior of known error is no better than the prior (its cost is not
#: lower) or the refined pose's uncertainty is unbounded
PRIOR_MORE_PRECISE = "prior more precise"
#: ``Verdict.rejected`` when the prior lies within the refined pose's own uncertainty (``MIN_PRIOR_DISTANCE``): the
#: refinement is not clearly better than the prior, so the prior is kept
WITHIN_UNCERTAINTY = "within uncertainty"
TRUST_REGION_EDGE = "trust-region edge"
#: ``Verdict.rejected`` when the candidate's cost lies above the map's declared cost level (``Tuning.map_cost_bound``)
ABOVE_MAP_LEVEL = "cost above the map's level"
WEAK_ALIGNMENT = "weak alignment"

logger = logging.getLogger("hgsloc_plugin")

MIN_SIGNIFICANCE = 1.0
MIN_SHARPNESS = 0.02
MIN_ALIGNMENT = 0.011
EDGE_FRACTION = 0.9
MAX_LEVEL_SHIFT = 6.0
#: a polished pose is returned only when the prior lies at least this many of its standard deviations from it
#: (Mahalanobis distance in the 6 pose axes, :func:`prior_distance`); a prior of known error is fused instead
MIN_PRIOR_DISTANCE = 3.0
#: the rendered rises follow the polish's model when their ratios to its predictions spread at most this much
#: (1.1-1.9 at accepted snow candidates, 2.45 at the least regular refused one: ``benchmarks/trust.md``)
MODEL_SPREAD = 2.0


@dataclass
class Assessment:
    """The acceptance rule's inputs and verdict for one query.

    Attributes:
        significance: (coarse cost - best cost) / kappa: the improvement in one-pixel rises.
        sharpness: smallest rendered axis rise / kappa (<= 0: some 1-px move does not raise the cost).
        travel: largest of shift / max_shift and rotation / max_rotation from the coarse pose, in [0, 1].
        level_shift: distance between the coarse levels' best pose and the final one, in coarsest steps.
        kappa: median one-pixel rise of the cost at the best pose.
        alignment: kappa / best cost (nan when not checked; inf at a best cost of zero or below, a perfect match
            up to rounding, with a positive kappa).
        confidence: summary in [0, 1]: min(1, significance / 4) * min(1, sharpness / 0.1) * (1 - travel^4);
            0 when rejected (an accepted polished pose's verdict replaces it by :func:`within_tolerance` under the
            rule's covariance).
        rejected: None when accepted, else the reason ("insignificant", "flat valley", ...).
        prior_distance: the prior's Mahalanobis distance from a polished pose under the rule's covariance
            (``uncertainty.pose_uncertainty``, :func:`prior_distance`; nan when not measured).
        within: :func:`within_tolerance` of a polished pose under the rule's covariance, accepted or not (nan
            when not measured).
    """

    significance: float
    sharpness: float
    travel: float
    level_shift: float
    kappa: float
    alignment: float
    confidence: float
    rejected: str | None
    prior_distance: float = math.nan
    within: float = math.nan

    def to_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in vars(self).items()}


def settled(a: Assessment) -> bool:
    """Whether a pose refused only for lack of improvement sits in a sharp, well-aligned minimum (every other
    test passes): the coarse pose is already as good as the map can tell, so a search from it is not run
    (``RefineConfig.routes``)."""
    return (a.rejected in ("insignificant", "no improvement")
            and _shape_reason(a.alignment, a.sharpness, a.travel, a.level_shift, not math.isnan(a.alignment)) is None)


def _shape_reason(alignment: float, sharpness: float, travel: float, level_shift: float,
                  check_alignment: bool) -> str | None:
    """The rule's tests after the improvement ones, in order: the first that fails, or None."""
    if check_alignment and not alignment >= MIN_ALIGNMENT:
        return WEAK_ALIGNMENT
    if not sharpness >= MIN_SHARPNESS:
        return "flat valley"
    if travel > EDGE_FRACTION:
        return TRUST_REGION_EDGE
    if level_shift > MAX_LEVEL_SHIFT:
        return "level inconsistency"
    return None


def assess(cost_initial: float, cost_best: float, rises: np.ndarray, travel: float, level_shift: float, *,
           check_alignment: bool = False, middle: np.ndarray | None = None) -> Assessment:
    """Apply the acceptance rule.

    Args:
        cost_initial / cost_best: the coarse pose's and the search's best cost at the final resolution.
        rises: [M] cost of one-pixel axis moves around the best pose minus ``cost_best``: all 12, or the ones
            ``model_moves`` picks (the lowest is the sharpness).
        travel: fraction of the trust region used (shift or rotation, the larger).
        level_shift: in coarsest-level steps.
        check_alignment: apply the "weak alignment" test (for the structural costs cs, ssim, ncc).
        middle: the rises kappa is the median of (``model_moves``' middle four); None: all of ``rises``.
    """
    rises = np.asarray(rises, dtype=np.float64)
    at = rises if middle is None else np.asarray(middle, dtype=np.float64)
    kappa = float(np.median(at)) if at.size else math.nan
    drop = cost_initial - cost_best
    scale = kappa if kappa > 0 else math.inf
    significance = drop / scale
    sharpness = float(rises.min()) / scale if rises.size else math.nan
    alignment = math.nan
    if check_alignment:  # a cost at zero (or a rounding below it: a perfect match) is perfectly aligned
        alignment = kappa / cost_best if cost_best > 0 else (math.inf if kappa > 0 else math.nan)
    if not drop > 0:
        reason = "no improvement"
    elif not significance >= MIN_SIGNIFICANCE:
        reason = "insignificant"
    else:
        reason = _shape_reason(alignment, sharpness, travel, level_shift, check_alignment)
    conf = 0.0
    if reason is None:
        conf = min(1.0, significance / 4.0) * min(1.0, sharpness / 0.1) * (1.0 - min(travel, 1.0) ** 4)
    return Assessment(float(significance), float(sharpness), float(travel), float(level_shift), kappa,
                      float(alignment), float(conf), reason)


@dataclass
class Verdict:
    """What the rule decided about a candidate: the returned pose and its cost (the coarse pose and its cost when
    refused), why it was refused (None: accepted), the rule's measurements, the confidence (nan when nothing was
    measured), whether the pose is a fusion with the prior, and its returned covariance [6, 6] and sigmas (scene
    units, degrees; ``uncertainty.pixel_noise_uncertainty``, through the fusion) and the rule's covariance [6, 6]
    (``uncertainty.pose_uncertainty``, through the fusion) when known."""

    pose: Pose
    cost: float
    rejected: str | None
    assessment: Assessment | None = None
    confidence: float = 0.0
    fused: bool = False
    covariance: np.ndarray | None = None
    sigma_t: float = math.nan
    sigma_r_deg: float = math.nan
    rule_covariance: np.ndarray | None = None

    @property
    def accepted(self) -> bool:
        return self.rejected is None

    def ends_refinement(self) -> bool:
        """Whether no (wider) search should follow this verdict: the candidate was accepted, the prior is more
        precise than the fusion near it or lies within the refinement's uncertainty, or the coarse pose sits in a
        sharp, aligned minimum."""
        return (self.accepted or self.rejected in (PRIOR_MORE_PRECISE, WITHIN_UNCERTAINTY)
                or (self.assessment is not None and settled(self.assessment)))


def judge(cand: Candidate, plan: Plan, scorer: Scorer, cam: Camera, *, rule: str, lattice: bool, structural: bool,
          pivot: bool, floor: tuple[float, float] = (FLOOR_DEPTH, FLOOR_DEG), cost_bound: float | None = None,
          name: str | None = None) -> Verdict:
    """Apply the acceptance rule (``rule`` "trust", on the lattice; else "cost": any lower cost) to ``cand``, then
    fuse an accepted polished pose with a prior of known error. ``scorer`` scores at ``cam``, the judging size;
    ``structural``: the cost's level is comparable across images (the alignment test applies); ``floor``: the map's
    floor (fraction of the depth, degrees) in a polished pose's covariance; ``cost_bound``: the map's cost level
    (``Tuning.map_cost_bound``; None: none), above which the candidate is refused.

    Everything the rule may need is scored in one batch: the coarse pose and the candidate (their costs are set on
    ``cand``), the one-pixel moves (6 of the 12 for a polished candidate, ``model_moves``; the other 6 in a second
    batch where their rises do not follow the model), and the fusion with the prior (scored before the verdict; used
    only when the candidate is accepted). A candidate whose cost the polish's line search rendered at ``cam``'s size
    is not rendered again (``PolishStats.cost_rendered``)."""
    coarse = plan.coarse_pose
    trust = rule == "trust" and lattice
    moves = pixel_moves(cand.pose, plan, cam, pivot) if trust else []
    model = model_moves(cand, moves, cam)
    first = moves if model is None else [moves[i] for i in model[0]]
    uncertainty = returned = None  # the rule's covariance and sigmas, and the returned ones
    if cand.polish:
        jtj, band_grads, noise = scorer.gradient_noise(cand.pose, BANDS)
        uncertainty = pose_uncertainty(jtj, band_grads, plan.depth, *floor)
        returned = pixel_noise_uncertainty(jtj, noise, plan.depth, *floor)
    fuses = uncertainty is not None and (plan.prior_error is not None or plan.prior_error_deg is not None)
    fusion = None  # (fused pose, its covariance): a polished pose of bounded uncertainty and a prior of known error
    if fuses and np.all(np.isfinite(uncertainty[0])):
        fusion = fuse_with_prior(cand.pose, uncertainty[0], coarse, plan.prior_error, plan.prior_error_deg)
    last = last_stage_at(cand, cam)
    if last is not None and math.isfinite(last.cost_rendered):
        scorer.remember(cand.pose, last.cost_rendered, "cs")  # the polish's line search rendered it at this size
    costs = scorer([coarse, cand.pose, *first] + ([fusion[0]] if fusion is not None else []))
    cand.cost_initial, cand.cost = float(costs[0]), float(costs[1])
    fused_cost = float(costs[-1]) if fusion is not None else math.nan
    rejected, assessment, confidence = None, None, 0.0
    if trust:
        rises, middle = costs[2:2 + len(first)] - cand.cost, None
        if model is not None:
            if model_agrees(rises, model[1]):
                middle = rises[2:]
            else:  # the other six too (the scorer keeps the rendered ones' costs)
                logger.debug("query %s: the rule renders all 12 moves (rises %s off the model %s)", name, rises,
                             model[1])
                rises = scorer(moves) - cand.cost
        assessment = _assess(cand, plan, rises, structural, middle)
        rejected, confidence = assessment.rejected, assessment.confidence
        if uncertainty is not None:
            assessment.prior_distance = prior_distance(cand.pose, uncertainty[0], coarse)
            assessment.within = within_tolerance(uncertainty[1], uncertainty[2], plan.depth)
            if rejected is None and not fuses and assessment.prior_distance < MIN_PRIOR_DISTANCE:
                rejected = WITHIN_UNCERTAINTY
    elif not cand.cost < cand.cost_initial:
        rejected = "no improvement"
    if rejected is None and cost_bound is not None and not cand.cost <= cost_bound:
        rejected = ABOVE_MAP_LEVEL
    pose, cost, fused = cand.pose, cand.cost, False
    if rejected is None and fuses:
        fused = fused_cost < cand.cost_initial  # nan (no fusion) is not
        logger.debug("query %s: fused with the prior (expected error %s / %s deg): cost %.6g, coarse %.6g", name,
                     plan.prior_error, plan.prior_error_deg, fused_cost, cand.cost_initial)
        if fused:
            if np.all(np.isfinite(returned[0])):  # the fusion weighed the refined pose by the rule's covariance
                cov = fused_covariance(returned[0], uncertainty[0], plan.prior_error, plan.prior_error_deg)
                returned = (cov, *sigmas(cov))
            pose, cost, uncertainty = fusion[0], fused_cost, (fusion[1], *sigmas(fusion[1]))
        else:  # the fusion is no better than the prior, or the refined pose's uncertainty is unbounded
            rejected = PRIOR_MORE_PRECISE
    if rejected is not None:
        logger.debug("query %s: %s pose rejected (%s): %s", name, cand.route, rejected,
                     assessment.to_dict() if assessment else {})
        return Verdict(coarse, cand.cost_initial, rejected, assessment, 0.0)
    out = Verdict(pose, cost, None, assessment, confidence if assessment is not None else math.nan, fused)
    if returned is not None:
        out.covariance, out.sigma_t, out.sigma_r_deg = returned
        out.rule_covariance = uncertainty[0]
        if assessment is not None:  # under the rule's covariance: what the bands' disagreement says is kept in it
            out.confidence = within_tolerance(uncertainty[1], uncertainty[2], plan.depth)
    return out


def pixel_moves(best: Pose, plan: Plan, cam: Camera, pivot: bool) -> list[Pose]:
    """The 12 lattice moves of one pixel of image motion at ``cam``'s size around ``best``."""
    from .search import LatticeSpace

    f = 0.5 * (cam.fx + cam.fy)
    space = LatticeSpace(best, 1.0 / f, plan.depth / f, plan.depth if pivot else 0.0)
    return [space.pose(k) for k in space.neighbours((0,) * 6)]


def last_stage_at(cand: Candidate, cam: Camera | None) -> PolishStats | None:
    """``cand``'s last polish stage if it ran at ``cam``'s size (the rule's), else None."""
    if not cand.polish or cam is None:
        return None
    last = cand.polish[-1]
    return last if (last.width, last.height) == (cam.width, cam.height) else None


def predicted_rises(cand: Candidate, moves: list[Pose], cam: Camera) -> np.ndarray | None:
    """The rises [12] of the 12 one-pixel ``moves`` around ``cand`` that its last polish stage's Gauss-Newton model
    predicts (``g.xi + xi' JtJ xi / 2``); None without a finite model at ``cam``'s size."""
    last = last_stage_at(cand, cam) if len(moves) == 12 else None
    if last is None or last.grad is None:
        return None
    H, g = np.asarray(last.jtj, np.float64), np.asarray(last.grad, np.float64)
    if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
        return None
    xi = np.array([cand.pose.offset_in_camera(m) for m in moves])
    return xi @ g + 0.5 * np.einsum("ni,ij,nj->n", xi, H, xi)


def picked_moves(predicted: np.ndarray) -> list[int]:
    """Indices of the 6 moves the rule renders first, from their ``predicted`` rises [12]: the two ranked lowest
    (the flattest axis), then the four ranked 5th to 8th (the middle, whose median is kappa)."""
    order = np.argsort(predicted, kind="stable")
    return [int(i) for i in (*order[:2], *order[4:8])]


def model_moves(cand: Candidate, moves: list[Pose], cam: Camera) -> tuple[list[int], np.ndarray] | None:
    """The 6 of the 12 one-pixel ``moves`` the rule renders first for ``cand`` (:func:`picked_moves` of
    :func:`predicted_rises`) and their predicted rises [6]; None (render all 12) without a model."""
    predicted = predicted_rises(cand, moves, cam)
    if predicted is None:
        return None
    picked = picked_moves(predicted)
    return picked, predicted[picked]


def model_agrees(rises: np.ndarray, predicted: np.ndarray) -> bool:
    """Whether rendered ``rises`` [M] follow the model's ``predicted`` [M]: every one positive and their ratios
    within a factor ``MODEL_SPREAD`` of each other."""
    rises, predicted = np.asarray(rises, np.float64), np.asarray(predicted, np.float64)
    if not (np.all(rises > 0) and np.all(predicted > 0)):
        return False
    ratio = rises / predicted
    return bool(ratio.max() <= MODEL_SPREAD * ratio.min())


def _assess(cand: Candidate, plan: Plan, rises: np.ndarray, structural: bool,
            middle: np.ndarray | None = None) -> Assessment:
    """:func:`assess` of the candidate from the rises of its rendered one-pixel moves (``middle``: as there)."""
    best = cand.pose
    step_r, step_t = plan.levels[0]
    after = cand.after_coarse
    level_shift = max(float(np.linalg.norm(after.centre() - best.centre())) / max(step_t, 1e-12),
                      rotation_angle_deg(after.R, best.R) / max(step_r, 1e-12))
    return assess(cand.cost_initial, cand.cost, rises, plan.travel(best), level_shift, check_alignment=structural,
                  middle=middle)
