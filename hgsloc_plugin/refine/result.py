"""What a refinement returns: :class:`RefineResult` (with ``search.LevelStats`` per search level)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..core.pose import Pose
from .polish import PolishStats
from .search import LevelStats
from .trust import Assessment


@dataclass
class RefineResult:
    """The result of one query. Poses are world-to-camera; lengths in scene units; angles in degrees.

    Attributes:
        pose: the returned pose: the refined one when ``accepted``, else the coarse pose.
        initial_pose: the coarse pose given.
        cost_initial / cost_final: the cost (lower is better) of the coarse and the returned pose at the size
            where the acceptance rule judged (the polish's when it runs, else the final scoring size).
        accepted: the refined pose passed the acceptance rule (``refine/trust.py``) and is returned.
        confidence: in [0, 1], 0 when not accepted; for a polished pose, the probability under the rule's
            covariance (``uncertainty.pose_uncertainty``, wider than ``covariance``) that it lies within 1 % of the
            median depth and 1 degree of the truth (``uncertainty.within_tolerance``); a ranking of right answers
            above wrong ones more than a calibrated probability; nan with ``acceptance="cost"`` (nothing measured).
        sigma_t / sigma_r_deg / covariance: the returned pose's estimated standard deviations (3-D: the root of
            each covariance block's trace, so an honest one holds the error within 1 sigma about 61 % of the
            time) and the [6, 6] covariance of ``xi = (w, v)`` (``Pose.perturbed_in_camera``): the image's
            pixel noise plus the map's floor (``uncertainty.pixel_noise_uncertainty``); nan / None when not
            measured. rule_covariance: the wider [6, 6] covariance the rule weighed by (the prior's distance, the
            fusion, the confidence: ``uncertainty.pose_uncertainty``); None when not measured.
        fused: the returned pose is the refined one fused with the prior of known error.
        rejected: why the refined pose was not returned ("no improvement", "insignificant", "weak alignment",
            "flat valley", "trust-region edge", "level inconsistency", "prior more precise", "within uncertainty",
            "cost above the map's level"); None when accepted.
        search_pose / search_cost: the pose the acceptance rule judged and its cost, returned or not.
        assessment: the rule's measurements.
        max_shift / max_rotation_deg: the trust region the query ran with.
        prior_error / prior_error_deg: the prior's expected error it ran with (nan: unknown).
        expansions / renders: search expansions and plain renders (the polish's line search included);
            levels: per-level details; history: best cost after each expansion; seconds: wall time.
        working_set / working_set_selections: Gaussians rendered (the largest selection) and selections made.
        route: "gradient" (the polish alone from the coarse pose), "wide gradient" (the polish from the coarse
            pose started at the wide search's size: a gradient pose that travelled beyond a window's reach is
            checked against it, the lower cost returned), "search" (lattice search + polish) or "wide search"
            (``Tuning.wide_step_pixels``, after a refused search): the route of the returned candidate;
            gradient_rejected: why the gradient route's pose was refused before the search ran.
        polish: the Levenberg-Marquardt stages run, every route's (``PolishStats``).
        error: set when the query failed (then ``pose`` is the coarse pose).
    """

    pose: Pose
    initial_pose: Pose
    cost_initial: float = math.nan
    cost_final: float = math.nan
    accepted: bool = False
    confidence: float = 0.0
    sigma_t: float = math.nan
    sigma_r_deg: float = math.nan
    covariance: np.ndarray | None = None
    rule_covariance: np.ndarray | None = None
    rejected: str | None = None
    search_pose: Pose | None = None
    search_cost: float = math.nan
    assessment: Assessment | None = None
    expansions: int = 0
    renders: int = 0
    levels: list[LevelStats] = field(default_factory=list)
    seconds: float = 0.0
    history: list[float] = field(default_factory=list)
    error: str | None = None
    name: str | None = None
    working_set: int = 0
    working_set_selections: int = 0
    polish: list[PolishStats] = field(default_factory=list)
    route: str | None = None
    gradient_rejected: str | None = None
    fused: bool = False
    max_shift: float = math.nan
    max_rotation_deg: float = math.nan
    prior_error: float = math.nan
    prior_error_deg: float = math.nan

    @property
    def derivative_passes(self) -> int:
        return sum(p.passes for p in self.polish)

    @classmethod
    def failed(cls, coarse_pose, error: str, name: str | None = None, seconds: float = 0.0) -> RefineResult:
        """The result of a query that could not be refined: the coarse pose (identity if unusable), ``error``."""
        pose = coarse_pose if isinstance(coarse_pose, Pose) else Pose.identity()
        return cls(pose=pose, initial_pose=pose, error=error, name=name, seconds=seconds)

    def to_dict(self) -> dict:
        return {
            "name": self.name, "accepted": self.accepted, "confidence": round(self.confidence, 4),
            "sigma_t": self.sigma_t, "sigma_r_deg": self.sigma_r_deg,
            "covariance": self.covariance.tolist() if self.covariance is not None else None,
            "rejected": self.rejected, "cost_initial": self.cost_initial,
            "cost_final": self.cost_final, "expansions": self.expansions, "renders": self.renders,
            "seconds": round(self.seconds, 4), "error": self.error, "working_set": self.working_set,
            "working_set_selections": self.working_set_selections,
            "derivative_passes": self.derivative_passes, "route": self.route,
            "gradient_rejected": self.gradient_rejected, "fused": self.fused,
            "polish": [p.to_dict() for p in self.polish],
            "max_shift": self.max_shift, "max_rotation_deg": self.max_rotation_deg,
            "prior_error": self.prior_error, "prior_error_deg": self.prior_error_deg,
            "qvec": self.pose.qvec.tolist(), "tvec": self.pose.tvec.tolist(),
            "levels": [vars(lv) for lv in self.levels],
            "assessment": self.assessment.to_dict() if self.assessment else None,
            "search_qvec": self.search_pose.qvec.tolist() if self.search_pose is not None else None,
            "search_tvec": self.search_pose.tvec.tolist() if self.search_pose is not None else None,
        }
