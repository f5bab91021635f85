"""Refiner: refine one coarse camera pose by heuristic search over 3DGS renderings."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..image import check_size, load_image, resize_image
from ..kernels import RasterConfig
from ..lod import coarse_lod
from ..pose import Pose, rotation_angle_deg
from ..render import get_renderer
from ..scene import GaussianScene
from ..working_set import WorkingSet
from .config import RefineConfig
from .polish import MIN_STEP_PX, STAGE_STEP_PX, PolishStats, polish
from .scorer import Scorer
from .search import LatticeSpace, PaperSpace, best_first
from .trust import Assessment, assess, fuse_with_prior, pose_uncertainty, settled, sigmas

logger = logging.getLogger("hgsloc_plugin")


@dataclass
class LevelStats:
    """One step level: its steps, scoring size, expansions, renders, best cost and why it stopped."""

    step_rot_deg: float
    step_t: float
    width: int
    height: int
    expansions: int
    renders: int
    best_cost: float
    stopped: str


@dataclass
class RefineResult:
    """Result of one query.

    Attributes:
        pose: refined world-to-camera pose (the coarse pose when ``accepted`` is False).
        initial_pose: the coarse pose given.
        cost_initial / cost_final: heuristic of the coarse vs the returned pose at the size where the acceptance
            rule judged: the polish's when it runs (``polish_max_side``), else the final scoring size.
        accepted: the search's pose passed the acceptance rule (``RefineConfig.acceptance``) and is returned.
        confidence: in [0, 1], 0 when not accepted (``refine/trust.py``; the inputs are in ``assessment``).
        sigma_t / sigma_r_deg: estimated standard deviation of the returned pose's camera centre (scene units)
            and rotation (degrees), from the polish's Hessian (``trust.pose_uncertainty``, calibrated on real
            photos; the fusion's when ``fused``); nan when the search's pose was not returned or no polish ran.
            covariance: [6, 6] of the increment ``xi = (w, v)`` of ``Pose.perturbed_in_camera`` at the returned
            pose, or None.
        fused: the returned pose is the search's fused with the coarse pose of known expected error
            (``prior_error`` / ``prior_error_deg`` given: ``trust.fuse_with_prior``), not the search's itself.
        rejected: why the search's pose was not returned ("insignificant", "weak alignment", "flat valley",
            "trust-region edge", "level inconsistency", "no improvement", "prior more precise": its fusion with
            a prior of known error is no better than that prior), None when accepted or failed.
        search_pose / search_cost: the search's best pose (after the polish, when on) and its cost, returned or
            not: the pose the acceptance rule judged.
        assessment: the acceptance rule's measurements (significance, sharpness, travel, ...).
        max_shift / max_rotation_deg: the trust region the query ran with (scene units, degrees): the
            ``refine`` call's, else ``RefineConfig``'s, else the automatic one.
        prior_error / prior_error_deg: the coarse pose's expected error the query ran with (scene units,
            degrees; nan when not given): the ``refine`` call's, else ``RefineConfig``'s.
        expansions / renders: search effort (renders: every plain render of the query, the polish's line search
            included); levels: per-level details; seconds: wall time.
        working_set: Gaussians the search rendered (the largest of the query's working-set selections; the whole
            map when it is off); working_set_selections: selections made (0 when off).
        route: how the returned verdict was reached: "gradient" (the polish alone from the coarse pose, with
            ``gradient_first`` or search off) or "search" (the lattice search + polish); gradient_rejected: why the
            gradient route's pose was refused before the search ran (``gradient_first`` only), else None.
        polish: the Levenberg-Marquardt stages run (``refine/polish.py``: size, passes, last step, the 6x6 JtJ
            at the solution); empty when off. ``derivative_passes``: their derivative passes in all.
        history: best cost after each expansion (costs of different levels may use different resolutions).
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


def median_depth(scene: GaussianScene, camera: Camera, T_cam_world: Pose) -> float:
    """Median camera z of the Gaussian centres that project into the image (scene extent if none do)."""
    p = scene.means.astype(np.float64) @ T_cam_world.R.T + T_cam_world.tvec
    z = p[:, 2]
    front = z > 1e-6
    u = camera.fx * p[front, 0] / z[front] + camera.cx
    v = camera.fy * p[front, 1] / z[front] + camera.cy
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    zs = z[front][inside]
    return float(np.median(zs)) if zs.size else max(scene.extent(), 1e-6)


@dataclass
class _Plan:
    """What one query's search runs on: scoring cameras, step levels, depth and the trust region test."""

    cam_final: Camera
    cam_coarse: Camera
    cam_polish: Camera
    levels: list[tuple[float, float]]
    depth: float
    max_t: float
    max_r: float
    prior_t: float | None = None
    prior_r: float | None = None


#: what a query may set for itself (``Refiner.refine``'s keywords; also ``batch.Query``'s fields): its trust
#: region and its prior's expected error, absolute or as a fraction of the query's median depth
PER_QUERY = ("max_shift", "max_rotation_deg", "max_shift_depth", "prior_error", "prior_error_deg",
             "prior_error_depth")
#: ``RefineResult.rejected`` when the fusion with a prior of known error is no better than the prior (its cost is
#: not lower) or the refined pose's uncertainty is unbounded
PRIOR_MORE_PRECISE = "prior more precise"


class Refiner:
    """Pose refiner over one 3DGS scene, one query at a time.

    Example:
        >>> refiner = Refiner(scene)
        >>> result = refiner.refine(image, camera, coarse_pose)
        >>> result.pose, result.accepted

    Convention: poses are world-to-camera (COLMAP cam_from_world), quaternions w, x, y, z.
    """

    def __init__(self, scene: GaussianScene | str | Path, config: RefineConfig | None = None,
                 raster: RasterConfig | None = None):
        if isinstance(scene, (str, Path)):
            scene = GaussianScene.from_ply(scene)
        if not isinstance(scene, GaussianScene):
            raise TypeError(f"scene must be a GaussianScene or a path to a .ply, got {type(scene).__name__}")
        self.scene = scene
        if config is None and scene.white_background:  # recorded by the trainer (cfg_args)
            config = RefineConfig(background=(1.0, 1.0, 1.0))
        self.config = config or RefineConfig()
        self.raster = raster or RasterConfig()
        self.renderer = get_renderer(scene, self.raster)

    def _plan(self, camera: Camera, coarse: Pose, per_query: dict | None = None) -> _Plan:
        """The query's plan; ``per_query``: ``PER_QUERY`` keywords (None or absent: the config's, else
        automatic)."""
        cfg = self.config
        per_query = per_query or {}
        cam_final = camera.with_max_side(cfg.score_max_side)
        coarse_side = max(cfg.coarse_scale * max(cam_final.width, cam_final.height), cfg.coarse_min_side)
        cam_coarse = cam_final.with_max_side(int(round(coarse_side)))
        cam_polish = camera.with_max_side(cfg.polish_max_side)
        depth = median_depth(self.scene, cam_final, coarse)
        if cfg.neighbourhood == "paper":
            levels = [(cfg.paper_step_q, cfg.paper_step_t)]
        elif cfg.levels:
            levels = list(cfg.levels)
        else:
            f = 0.5 * (cam_final.fx + cam_final.fy)
            levels = [(math.degrees(px / f), px * depth / f) for px in cfg.step_pixels]
        if cfg.neighbourhood == "paper":  # raw-component steps: no image-motion scale
            auto_t, auto_r = 0.5 * depth, 10.0
        else:
            auto_t, auto_r = cfg.trust_steps * levels[0][1], cfg.trust_steps * levels[0][0]
        def pick(key: str, auto: float | None = None) -> float | None:
            v = per_query.get(key)
            if v is None and per_query.get(key + "_depth") is not None:
                v = per_query[key + "_depth"] * depth
            return next((u for u in (v, getattr(cfg, key)) if u is not None), auto)

        return _Plan(cam_final, cam_coarse, cam_polish, levels, depth, pick("max_shift", auto_t),
                     pick("max_rotation_deg", auto_r), pick("prior_error"), pick("prior_error_deg"))

    def refine(self, image, camera: Camera, coarse_pose: Pose, *, name: str | None = None,
               max_shift: float | None = None, max_rotation_deg: float | None = None,
               max_shift_depth: float | None = None, prior_error: float | None = None,
               prior_error_deg: float | None = None, prior_error_depth: float | None = None) -> RefineResult:
        """Refine one query.

        Args:
            image: [H, W, 3] uint8 or float in [0, 1], torch [3, H, W], or a path (grey and RGBA too, composited
                on ``RefineConfig.background``: ``image.load_image``); its size must match ``camera``.
            camera: the query's pinhole intrinsics at the image's size.
            coarse_pose: world-to-camera prior.
            max_shift / max_rotation_deg: this query's trust region (camera-centre shift in scene units, rotation
                in degrees), e.g. from the localizer's confidence in it (``adapters/confidence.py``); each
                overrides ``RefineConfig``'s when given.
            max_shift_depth: the shift bound as a fraction of the query's median depth (the one the search's
                steps are made from), used when ``max_shift`` is not given.
            prior_error / prior_error_deg: this prior's expected (median) error, camera centre in scene units
                and rotation in degrees (e.g. from the localizer's inlier count); an accepted refined pose is
                then fused with the prior, weighted by the two uncertainties (``RefineConfig.prior_error``).
                ``prior_error_depth``: the centre's as a fraction of the median depth.

        Returns:
            A :class:`RefineResult`; its pose is the search's only when that passes the acceptance rule
            (never a higher cost than the coarse pose; see ``refine/trust.py``), else the coarse pose.
        """
        t0 = time.perf_counter()
        cfg = self.config
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
        if not isinstance(coarse_pose, Pose):
            raise TypeError(f"coarse_pose must be a Pose, got {type(coarse_pose).__name__}")
        per_query = dict(zip(PER_QUERY, (max_shift, max_rotation_deg, max_shift_depth, prior_error,
                                         prior_error_deg, prior_error_depth)))
        for key, v in per_query.items():
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{key} must be a positive number, got {v}")
        img = load_image(image, name=name or "image", background=cfg.background)
        img = check_size(img, camera, cfg.resize_query, name or "image")
        plan = self._plan(camera, coarse_pose, per_query)
        renderer = self._working_set(plan, coarse_pose)
        scorer = Scorer(renderer, cfg.metric, cfg.background, cfg.mask_alpha)
        result = RefineResult(pose=coarse_pose, initial_pose=coarse_pose, name=name, working_set=renderer.n,
                              max_shift=plan.max_t, max_rotation_deg=plan.max_r,
                              prior_error=math.nan if plan.prior_t is None else plan.prior_t,
                              prior_error_deg=math.nan if plan.prior_r is None else plan.prior_r)
        try:
            self._run(plan, renderer, scorer, img, coarse_pose, result)
        finally:
            if isinstance(renderer, WorkingSet):
                result.working_set, result.working_set_selections = renderer.largest, renderer.selections
        result.renders = scorer.renders + sum(p.renders for p in result.polish)
        result.seconds = time.perf_counter() - t0
        return result

    def _run(self, plan: _Plan, renderer, scorer: Scorer, img: np.ndarray, coarse_pose: Pose,
             result: RefineResult) -> None:
        """The search, the polish and the acceptance rule of one query; fills ``result``. With
        ``gradient_first``, the gradient-only route is tried first; the search runs only when its pose is
        rejected, unless the coarse pose already sits in a sharp, well-aligned minimum (``trust.settled``)."""
        cfg = self.config
        if cfg.gradient_first and cfg.search and cfg.polishes and cfg.acceptance == "trust":
            self._attempt(plan, renderer, scorer, img, coarse_pose, result, search=False)
            # a prior more precise than the fusion near it is kept: the search cannot make that valley sharper
            if (result.accepted or result.rejected == PRIOR_MORE_PRECISE
                    or (result.assessment is not None and settled(result.assessment))):
                result.route = "gradient"
                return
            logger.debug("query %s: gradient route rejected (%s); searching", result.name, result.rejected)
            result.gradient_rejected = result.rejected
        self._attempt(plan, renderer, scorer, img, coarse_pose, result, search=cfg.search)
        result.route = "search" if cfg.search else "gradient"

    def _attempt(self, plan: _Plan, renderer, scorer: Scorer, img: np.ndarray, coarse_pose: Pose,
                 result: RefineResult, search: bool) -> None:
        """One route (the lattice search + polish, or the polish alone from the coarse pose) and the acceptance
        rule on its pose; sets the verdict fields of ``result`` (a later route overwrites them)."""
        cfg = self.config
        name = result.name
        # the rule judges where the candidate is a minimum: at the polish's size when it runs (a pose polished at
        # the query's own pixels is not the minimum of the 200 px cost, whose one-pixel moves may then descend)
        judge_cam = plan.cam_polish if cfg.polishes else plan.cam_final
        if search or judge_cam == plan.cam_final:  # the coarse cost at the scoring size: the search's start
            scorer.set_query(plan.cam_final, img, renderer=renderer)
            result.cost_initial = float(scorer([coarse_pose])[0])
        if search:
            best_pose, best_cost, after_coarse = self._search_levels(plan, scorer, img, coarse_pose, result)
        else:
            best_pose, best_cost, after_coarse = coarse_pose, result.cost_initial, coarse_pose
        if cfg.polishes:
            best_pose = self._polish(plan, renderer, img, best_pose, coarse_pose, result, search)
            if judge_cam != plan.cam_final:
                scorer.set_query(judge_cam, img, renderer=renderer)
                result.cost_initial = float(scorer([coarse_pose])[0])
            best_cost = float(scorer([best_pose])[0])
        result.search_pose, result.search_cost = best_pose, best_cost
        result.rejected, result.assessment, result.confidence = None, None, 0.0
        if cfg.acceptance == "trust" and cfg.neighbourhood == "lattice":
            result.assessment = self._assess(plan, judge_cam, scorer, coarse_pose, after_coarse, best_pose,
                                             best_cost, result.cost_initial)
            result.rejected = result.assessment.rejected
            result.confidence = result.assessment.confidence
        elif not best_cost < result.cost_initial:
            result.rejected = "no improvement"
        uncertainty = None  # the last polish stage's Hessian is at its best pose, the one judged
        result.fused = False
        if result.rejected is None and result.polish:
            last = result.polish[-1]
            uncertainty = pose_uncertainty(last.jtj, last.cost)
            if plan.prior_t is not None or plan.prior_r is not None:
                best_pose, best_cost, uncertainty = self._fuse(plan, scorer, best_pose, uncertainty, coarse_pose,
                                                               result)
        if result.rejected is None:
            result.pose, result.cost_final, result.accepted = best_pose, best_cost, True
            if uncertainty is not None:
                result.covariance, result.sigma_t, result.sigma_r_deg = uncertainty
            if result.assessment is None:  # cost-only acceptance measures nothing to be confident about
                result.confidence = math.nan
        else:
            result.confidence = 0.0
            result.pose, result.cost_final, result.accepted = coarse_pose, result.cost_initial, False
            logger.debug("query %s: %s pose rejected (%s): %s", name, "search" if search else "gradient",
                         result.rejected, result.assessment.to_dict() if result.assessment else {})

    @staticmethod
    def _fuse(plan: _Plan, scorer: Scorer, pose: Pose, uncertainty: tuple, coarse: Pose, result: RefineResult):
        """The accepted ``pose`` fused with the coarse pose of known expected error (``trust.fuse_with_prior``):
        (pose, its cost at the judging size, (covariance, sigma_t, sigma_r_deg)); sets ``result.fused``, or
        ``result.rejected`` to ``PRIOR_MORE_PRECISE`` when the fusion's cost is not below the coarse pose's (never
        worse in cost) or the refined pose's uncertainty is unbounded (the prior is then the more precise)."""
        cov = uncertainty[0]
        if not np.all(np.isfinite(cov)):
            result.rejected = PRIOR_MORE_PRECISE
            return pose, math.nan, None
        fused, post = fuse_with_prior(pose, cov, coarse, plan.prior_t, plan.prior_r)
        cost = float(scorer([fused])[0])
        logger.debug("query %s: fused with the prior (expected error %s / %s deg): cost %.6g, coarse %.6g",
                     result.name, plan.prior_t, plan.prior_r, cost, result.cost_initial)
        if not cost < result.cost_initial:
            result.rejected = PRIOR_MORE_PRECISE
            return pose, math.nan, None
        result.fused = True
        return fused, cost, (post, *sigmas(post))

    def _working_set(self, plan: _Plan, coarse: Pose):
        """The renderer the search uses: a :class:`WorkingSet` that follows the poses scored (region radius
        ``working_set_pixels`` of image motion at the final size), or the whole map when
        ``RefineConfig.working_set`` is off or the map has fewer than ``working_set_min`` Gaussians."""
        if not self.config.working_set or self.renderer.n < self.config.working_set_min:
            return self.renderer
        cam = plan.cam_final
        f = min(cam.fx, cam.fy)
        px = self.config.working_set_pixels
        return WorkingSet(self.renderer, [plan.cam_final, plan.cam_coarse, plan.cam_polish], px * plan.depth / f,
                          math.degrees(px / f))

    def _polish(self, plan: _Plan, renderer, img: np.ndarray, pose: Pose, coarse: Pose,
                result: RefineResult, search: bool) -> Pose:
        """Levenberg-Marquardt on the cs cost (``refine/polish.py``) at the polish size; without the search
        (gradient only), coarse to fine over the coarse, final and polish sizes. Appends to ``result.polish``."""
        cfg = self.config
        cams = [plan.cam_polish]
        if not search:
            cams = list(dict.fromkeys([plan.cam_coarse, plan.cam_final, plan.cam_polish]))
        allowed = self._trust_region(coarse, plan.max_t, plan.max_r)
        for i, cam in enumerate(cams):
            q = renderer.upload_window_query(resize_image(img, cam.width, cam.height))
            last = i == len(cams) - 1  # a stage before a finer one stops at a coarser step: the next goes on
            pose, stats = polish(renderer, cam, q, pose, depth=plan.depth, iterations=cfg.polish_iterations,
                                 allowed=allowed, background=cfg.background, mask_alpha=cfg.mask_alpha,
                                 min_step_px=MIN_STEP_PX if last else STAGE_STEP_PX)
            result.polish.append(stats)
        return pose

    def try_refine(self, image, camera: Camera, coarse_pose, *, name: str | None = None,
                   **per_query: float | None) -> RefineResult:
        """Like :meth:`refine` (``per_query``: its ``PER_QUERY`` keywords), but a failure (bad image, camera,
        pose) comes back as a failed result."""
        t0 = time.perf_counter()
        unknown = set(per_query) - set(PER_QUERY)
        if unknown:
            raise TypeError(f"try_refine got unexpected keywords {sorted(unknown)}; per-query ones: {PER_QUERY}")
        try:
            return self.refine(image, camera, coarse_pose, name=name, **per_query)
        except Exception as exc:  # recorded per query; a batch goes on
            logger.warning("query %s failed: %s", name, exc)
            return RefineResult.failed(coarse_pose, f"{type(exc).__name__}: {exc}", name,
                                       time.perf_counter() - t0)

    @staticmethod
    def _travel(a: Pose, b: Pose, max_t: float, max_r: float) -> float:
        """The larger of centre shift / max_t and rotation / max_r between two poses."""
        return max(float(np.linalg.norm(a.centre() - b.centre())) / max_t, rotation_angle_deg(a.R, b.R) / max_r)

    def _assess(self, plan: _Plan, cam: Camera, scorer: Scorer, coarse: Pose, after_coarse: Pose, best: Pose,
                best_cost: float, cost_initial: float) -> Assessment:
        """Score the 12 one-pixel moves around ``best`` at ``cam``'s size (the scorer's) and apply ``trust.assess``."""
        f = 0.5 * (cam.fx + cam.fy)
        space = LatticeSpace(best, 1.0 / f, plan.depth / f, plan.depth if self.config.pivot else 0.0)
        moves = space.neighbours((0,) * 6)
        rises = scorer([space.pose(k) for k in moves]) - best_cost
        travel = self._travel(coarse, best, plan.max_t, plan.max_r)
        step_r, step_t = plan.levels[0]
        level_shift = max(float(np.linalg.norm(after_coarse.centre() - best.centre())) / max(step_t, 1e-12),
                          rotation_angle_deg(after_coarse.R, best.R) / max(step_r, 1e-12))
        return assess(cost_initial, best_cost, rises, travel, level_shift,
                      check_alignment=self.config.metric in ("cs", "ssim", "ncc"))

    def _trust_region(self, coarse: Pose, max_t: float, max_r: float):
        c0, R0 = coarse.centre(), coarse.R

        def allowed(T: Pose) -> bool:
            if np.linalg.norm(T.centre() - c0) > max_t:
                return False
            return rotation_angle_deg(R0, T.R) <= max_r

        return allowed

    def _search_levels(self, plan: _Plan, scorer: Scorer, img: np.ndarray, coarse: Pose,
                       result: RefineResult) -> tuple[Pose, float]:
        """Run the step levels coarse to fine; returns the best pose, its cost at the final resolution and the best
        pose after the coarse (pyramid) levels."""
        cfg = self.config
        allowed = self._trust_region(coarse, plan.max_t, plan.max_r)
        best_pose, best_cost, best_cam = coarse, result.cost_initial, plan.cam_final
        after_coarse = coarse
        remaining = cfg.max_expansions
        exact, lod = scorer.renderer, None
        for li, (s_rot, s_t) in enumerate(plan.levels):
            if remaining <= 0:
                break
            is_coarse = li < cfg.coarse_levels and li < len(plan.levels) - 1
            cam_l = plan.cam_coarse if is_coarse else plan.cam_final
            if is_coarse and lod is None and cfg.coarse_lod_pixels is not None and isinstance(exact, WorkingSet):
                lod = coarse_lod(exact.full, plan.cam_coarse, coarse, plan.max_t, plan.max_r, cfg.coarse_lod_pixels)
            want = lod if is_coarse and lod is not None else exact
            if cam_l != best_cam or want is not scorer.renderer:
                scorer.set_query(cam_l, img, renderer=want)
                best_cost = float(scorer([best_pose])[0])
                best_cam = cam_l
            if cfg.neighbourhood == "paper":
                space = PaperSpace(best_pose, s_rot, s_t)
            else:
                space = LatticeSpace(best_pose, math.radians(s_rot), s_t, plan.depth if cfg.pivot else 0.0)
            lr = best_first(space, best_cost, scorer, allowed, budget=min(cfg.max_expansions_per_level, remaining),
                            patience=cfg.patience, weight=cfg.heuristic_weight, depth_cost=cfg.depth_cost,
                            pattern=cfg.pattern_moves and cfg.neighbourhood == "lattice")
            remaining -= lr.expansions
            best_pose, best_cost = space.pose(lr.best_key), lr.best_cost
            result.expansions += lr.expansions
            result.history.extend(lr.history)
            result.levels.append(LevelStats(s_rot, s_t, cam_l.width, cam_l.height, lr.expansions, lr.renders,
                                            lr.best_cost, lr.stopped))
            if is_coarse:
                after_coarse = best_pose
        if best_cam != plan.cam_final or scorer.renderer is not exact:
            scorer.set_query(plan.cam_final, img, renderer=exact)
            best_cost = float(scorer([best_pose])[0])
        return best_pose, best_cost, after_coarse
