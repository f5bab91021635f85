"""Refiner: refine one coarse camera pose on a 3DGS map.

``Refiner.refine`` reads top to bottom: plan (``plan.py``) -> gradient route (-> wide gradient route when it
travelled far) -> (search route) -> (wide search route) (``routes.py``), each judged by the acceptance rule
(``trust.judge``) -> result (``result.py``). Where the gradient route and the search agree (one minimum), the
search's pose is judged again: without the alignment test when both were refused for weak alignment only, in the
wide search's region when both were cut off by their own trust region's edge. Where the wide search's polished
hypotheses agree (``Candidate.agreeing``), its pose refused for weak alignment only is judged without that test.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

from ..core.backend import lod_cache_dir
from ..core.camera import Camera
from ..core.costs import METRICS
from ..core.image import check_size, load_image, undistort
from ..core.pose import Pose
from ..core.prior import QueryPrior
from ..core.scene import GaussianScene
from ..kernels import RasterConfig
from ..kernels.window import RADIUS as WINDOW_RADIUS
from ..render import RendererLike, get_renderer
from ..render.hierarchy import CutSelection, Hierarchy, hierarchy_for
from ..render.working_set import WorkingSet
from .config import RefineConfig
from .plan import Plan, make_plan
from .result import RefineResult
from .routes import Candidate, QueryContext, gradient_route, search_route, wide_gradient_route, wide_search_route
from .scorer import Scorer
from .trust import TRUST_REGION_EDGE, WEAK_ALIGNMENT, Verdict, judge

logger = logging.getLogger("hgsloc_plugin")

#: what a query may set for itself (``Refiner.refine``'s keywords, a query dict's keys): ``QueryPrior``'s fields
PER_QUERY = QueryPrior.names()


class Refiner:
    """Pose refiner over one 3DGS scene, one query at a time.

    Example:
        >>> refiner = Refiner(scene)
        >>> result = refiner.refine(image, camera, coarse_pose)
        >>> result.pose, result.accepted

    Convention: poses are world-to-camera (COLMAP cam_from_world), quaternions w, x, y, z.
    """

    def __init__(self, scene: GaussianScene | str | Path, config: RefineConfig | None = None,
                 raster: RasterConfig | None = None, renderer: RendererLike | None = None):
        if isinstance(scene, (str, Path)):
            scene = GaussianScene.from_ply(scene)
        if not isinstance(scene, GaussianScene):
            raise TypeError(f"scene must be a GaussianScene or a path to a .ply, got {type(scene).__name__}")
        self.scene = scene
        if config is None and scene.white_background:  # recorded by the trainer (cfg_args)
            config = RefineConfig(background=(1.0, 1.0, 1.0))
        self.config = config or RefineConfig()
        self.raster = raster or RasterConfig()
        self.renderer = renderer if renderer is not None else get_renderer(scene, self.raster)
        #: whether the renderer was given (another backend) rather than built from the scene and ``raster``
        self.renderer_given = renderer is not None
        #: a trace hook for measurements (benchmarks): called as ``on_judged(candidate, verdict, plan)`` after the
        #: acceptance rule judged each route's candidate, in the order they ran; None: nothing is called
        self.on_judged: Callable[[Candidate, Verdict, Plan], None] | None = None
        #: a trace hook for measurements: called as ``on_stage(stage, seconds)`` after each search level
        #: ("search WxH"), polish stage ("polish WxH") and acceptance rule ("rule"); None: nothing is called
        self.on_stage: Callable[[str, float], None] | None = None
        self._hierarchy: Hierarchy | None = None

    def refine(self, image, camera: Camera, coarse_pose: Pose, *, name: str | None = None,
               prior: QueryPrior | None = None, **settings: float | None) -> RefineResult:
        """Refine one query.

        Args:
            image: [H, W, 3] uint8 or float in [0, 1], torch [3, H, W], or a path (grey and RGBA too, composited
                on ``RefineConfig.background``); its size must match ``camera``.
            camera: the query's intrinsics at the image's size; a camera with lens distortion
                (``Camera.distortion``) has its photo undistorted to a pinhole camera first (``image.undistort``).
            coarse_pose: world-to-camera prior.
            prior: this query's trust region and expected prior error (:class:`QueryPrior`); or its fields as
                keywords (``max_shift=0.1, prior_error_deg=1.0``, ...). Each overrides ``RefineConfig``'s.

        Returns:
            A :class:`RefineResult`; its pose is the refined one only when that passes the acceptance rule
            (``refine/trust.py``), else the coarse pose.
        """
        t0 = time.perf_counter()
        cfg = self.config
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")
        if not isinstance(coarse_pose, Pose):
            raise TypeError(f"coarse_pose must be a Pose, got {type(coarse_pose).__name__}")
        prior = _query_prior(prior, settings)
        img = load_image(image, name=name or "image", background=cfg.background)
        img = check_size(img, camera, cfg.resize_query, name or "image")
        img, camera = undistort(img, camera)  # a photo through a lens with distortion: to its pinhole camera

        plan = make_plan(cfg, self.scene, camera, coarse_pose, prior)
        renderer = self.renderer_for(plan)
        ctx = QueryContext(cfg, plan, renderer, Scorer(renderer, cfg.metric, cfg.background, cfg.tuning.mask_alpha),
                           img, name, self.on_stage)
        routes = cfg.route_choice()
        main_route = search_route if routes.main == "search" else gradient_route
        tried: list[tuple[Candidate, Verdict]] = []
        if routes.gradient_first:
            tried.append(self._judged(ctx, gradient_route(ctx)))
            if not tried[-1][1].ends_refinement():
                logger.debug("query %s: gradient route rejected (%s); searching", name, tried[-1][1].rejected)
            elif tried[-1][1].accepted and _beyond_reach(plan, tried[-1][0]):
                logger.debug("query %s: the gradient route travelled beyond a window's reach; the polish from the "
                             "wide search's size checks it", name)
                tried = _lower_cost_last([tried[-1], self._judged(ctx, wide_gradient_route(ctx))])
        if not tried or not tried[-1][1].ends_refinement():
            tried.append(self._judged(ctx, main_route(ctx)))
            if _agree_but_weakly_aligned(tried, plan, cfg.tuning.same_minimum_pixels):
                logger.debug("query %s: gradient route and search agree, refused for weak alignment only; the "
                             "rule judges the search's pose on their agreement instead", name)
                tried.append(self._judged(ctx, tried[-1][0], structural=False))
        if routes.wide and not tried[-1][1].ends_refinement():
            if _same_minimum(tried[:2], plan, cfg.tuning.same_minimum_pixels):
                logger.debug("query %s: gradient route and search refused in one minimum (%s); no wide search", name,
                             tried[-1][1].rejected)
                return _result(ctx, tried, time.perf_counter() - t0)
            wide = make_plan(cfg, self.scene, camera, coarse_pose, prior, cfg.tuning.wide_step_pixels)
            if wide.max_shift <= plan.max_shift and wide.max_rotation_deg <= plan.max_rotation_deg:
                logger.debug("query %s: search rejected (%s); its trust region leaves a wide search no room", name,
                             tried[-1][1].rejected)
                return _result(ctx, tried, time.perf_counter() - t0)
            ctx = dataclasses.replace(ctx, plan=wide)
            if _agree_at_edge(tried, plan, cfg.tuning.same_minimum_pixels):
                logger.debug("query %s: gradient route and search agree at their trust region's edge; the rule "
                             "judges the search's pose in the wide search's region", name)
                tried.append(self._judged(ctx, tried[-1][0]))
                if tried[-1][1].ends_refinement():
                    return _result(ctx, tried, time.perf_counter() - t0)
            logger.debug("query %s: search rejected (%s); searching wide", name, tried[-1][1].rejected)
            tried.append(self._judged(ctx, wide_search_route(ctx)))
            if tried[-1][1].rejected == WEAK_ALIGNMENT and tried[-1][0].agreeing:
                logger.debug("query %s: the wide search's hypotheses agree, refused for weak alignment only; the rule "
                             "judges its pose on their agreement instead", name)
                tried.append(self._judged(ctx, tried[-1][0], structural=False))
        return _result(ctx, tried, time.perf_counter() - t0)

    def _judged(self, ctx: QueryContext, cand: Candidate, structural: bool = True) -> tuple[Candidate, Verdict]:
        """``cand`` and the rule's verdict on it; ``structural`` False: without the alignment test."""
        cfg = self.config
        with ctx.timed("rule"):
            verdict = judge(cand, ctx.plan, ctx.scorer, ctx.judge_cam, rule=cfg.acceptance,
                            lattice=cfg.tuning.neighbourhood == "lattice",
                            structural=structural and METRICS[cfg.metric].structural, pivot=cfg.tuning.pivot,
                            floor=(cfg.tuning.map_floor_depth, cfg.tuning.map_floor_deg),
                            cost_bound=cfg.tuning.map_cost_bound, name=ctx.name)
        if self.on_judged is not None:
            self.on_judged(cand, verdict, ctx.plan)
        return cand, verdict

    def renderer_for(self, plan: Plan) -> RendererLike:
        """The renderer the routes use: a :class:`WorkingSet` that follows the poses scored (region radius
        ``working_set_pixels`` of image motion at the final size), or the whole map when
        ``Tuning.working_set`` is off or the map has fewer than ``working_set_min`` Gaussians."""
        if not self.config.tuning.working_set or self.renderer.n < self.config.tuning.working_set_min:
            return self.renderer
        cam = plan.cam_final
        f = min(cam.fx, cam.fy)
        px = self.config.tuning.working_set_pixels
        lod = self.config.tuning.lod_pixels
        return WorkingSet(self.renderer, [plan.cam_final, plan.cam_coarse, plan.cam_polish, plan.cam_wide],
                          px * plan.depth / f, math.degrees(px / f),
                          select=None if lod is None else CutSelection(self.renderer, self.hierarchy(), lod),
                          per_camera=lod is not None)

    def hierarchy(self) -> Hierarchy:
        """The map's level-of-detail hierarchy (``render/hierarchy.py``), built on first use or read from the cache
        (``HGSLOC_LOD_CACHE_DIR``); needs the package's renderer (ValueError for a renderer given)."""
        if self._hierarchy is None:
            if self.renderer_given:
                raise ValueError("Tuning.lod_pixels needs the package's renderer; this refiner was given its own")
            self._hierarchy = hierarchy_for(self.renderer.arrays(), self.renderer.source_index, lod_cache_dir())
        return self._hierarchy

    def try_refine(self, image, camera: Camera, coarse_pose, *, name: str | None = None,
                   prior: QueryPrior | None = None, **settings: float | None) -> RefineResult:
        """Like :meth:`refine`, but a failure (bad image, camera, pose) comes back as a failed result."""
        t0 = time.perf_counter()
        unknown = set(settings) - set(PER_QUERY)
        if unknown:
            raise TypeError(f"try_refine got unexpected keywords {sorted(unknown)}; per-query ones: {PER_QUERY}")
        try:
            return self.refine(image, camera, coarse_pose, name=name, prior=prior, **settings)
        except Exception as exc:  # recorded per query; a batch goes on
            logger.warning("query %s failed: %s", name, exc)
            return RefineResult.failed(coarse_pose, f"{type(exc).__name__}: {exc}", name,
                                       time.perf_counter() - t0)


def _beyond_reach(plan: Plan, cand: Candidate) -> bool:
    """Whether the gradient route moved its pose further from the prior than the cs cost's window reaches at the
    route's coarsest size (``kernels.window.RADIUS`` pixels there): beyond that the descent followed structure
    no window saw whole, where a periodic texture or the rotation / translation ambiguity can hold it in a wrong
    minimum, so the polish from the prior started at the wide search's size (``routes.wide_gradient_route``,
    where such texture is blurred away) runs as a second hypothesis (``_lower_cost_last``)."""
    return plan.pixels_apart(plan.coarse_pose, cand.pose, plan.cam_coarse) > WINDOW_RADIUS


def _lower_cost_last(tried: list[tuple[Candidate, Verdict]]) -> list[tuple[Candidate, Verdict]]:
    """Two judged hypotheses, the one to return last: the accepted one of lower cost at the judging size (both
    were scored there, by the same scorer), else the accepted one, else the first."""
    (a, va), (b, vb) = tried
    if vb.accepted and (not va.accepted or b.cost < a.cost):
        return [(a, va), (b, vb)]
    return [(b, vb), (a, va)]


def _agree_but_weakly_aligned(tried: list[tuple[Candidate, Verdict]], plan: Plan, pixels: float) -> bool:
    """Whether the gradient route and the search were both refused for "weak alignment" only, at poses within
    ``pixels`` of each other (:func:`_same_minimum`): two explorations from different starts (one descends from
    the prior, one searches a lattice around it) found one minimum in a view whose cost is flat compared with
    its level (a plain or noisy view, shadows the map does not hold). Their agreement is the evidence the
    alignment ratio stands in for, so the search's pose is judged again without that test; every other test
    applies. A far wrong minimum that one route reaches and the other does not stays refused."""
    return (_same_minimum(tried, plan, pixels)
            and all(v.rejected == WEAK_ALIGNMENT for _, v in tried))


def _agree_at_edge(tried: list[tuple[Candidate, Verdict]], plan: Plan, pixels: float) -> bool:
    """Whether the gradient route and the search were both refused at the trust region's edge only, at poses within
    ``pixels`` of each other: two explorations from different starts reached one minimum that the region cut off
    (a prior farther off than the region allows). The wide search's larger region is the one to judge it in,
    every test applying, before searching that region from the prior."""
    return all(v.rejected == TRUST_REGION_EDGE for _, v in tried) and _routes_meet(tried, plan, pixels)


def _same_minimum(tried: list[tuple[Candidate, Verdict]], plan: Plan, pixels: float) -> bool:
    """Whether the gradient route and the search were both refused, neither at the trust region's edge, at poses
    within ``pixels`` of image motion at the final size (centre shift at the plan's depth plus rotation): the
    map's own minimum near the prior, where a wide search finds nothing else (``Tuning.same_minimum_pixels``)."""
    return (not any(v.rejected in (None, TRUST_REGION_EDGE) for _, v in tried)
            and _routes_meet(tried, plan, pixels))


def _routes_meet(tried: list[tuple[Candidate, Verdict]], plan: Plan, pixels: float) -> bool:
    """Whether ``tried`` is the gradient route then the search, ending within ``pixels`` (> 0) of image motion at the
    final size of each other."""
    return (len(tried) == 2 and tried[0][0].route == "gradient" and pixels > 0
            and plan.pixels_apart(tried[0][0].pose, tried[1][0].pose) <= pixels)


def _query_prior(prior: QueryPrior | None, settings: dict) -> QueryPrior:
    """``prior``, or one made of ``QueryPrior`` keywords (not both)."""
    unknown = sorted(set(settings) - set(PER_QUERY))
    if unknown:
        raise TypeError(f"refine got unexpected keywords {unknown}; per-query ones: {PER_QUERY}")
    given = {k: v for k, v in settings.items() if v is not None}
    if prior is not None:
        if given:
            raise TypeError(f"give the query's settings as prior= or as keywords, not both (got {sorted(given)})")
        return prior
    return QueryPrior(**given)


def _result(ctx: QueryContext, tried: list[tuple[Candidate, Verdict]], seconds: float) -> RefineResult:
    """The result of a query from the routes tried, in order, and their verdicts (the last one decides)."""
    plan = ctx.plan
    cand, verdict = tried[-1]
    polish = [s for c, _ in tried for s in c.polish]
    renderer = ctx.renderer
    res = RefineResult(
        pose=verdict.pose, initial_pose=plan.coarse_pose, name=ctx.name,
        cost_initial=cand.cost_initial, cost_final=verdict.cost, accepted=verdict.accepted,
        confidence=verdict.confidence, sigma_t=verdict.sigma_t, sigma_r_deg=verdict.sigma_r_deg,
        covariance=verdict.covariance, rule_covariance=verdict.rule_covariance, rejected=verdict.rejected,
        search_pose=cand.pose, search_cost=cand.cost,
        assessment=verdict.assessment, fused=verdict.fused, polish=polish,
        expansions=sum(c.expansions for c, _ in tried), history=[h for c, _ in tried for h in c.history],
        levels=[lv for c, _ in tried for lv in c.levels],
        route=cand.route, gradient_rejected=tried[0][1].rejected if len(tried) > 1 and tried[0][0].route == "gradient"
        else None,
        max_shift=plan.max_shift, max_rotation_deg=plan.max_rotation_deg,
        prior_error=math.nan if plan.prior_error is None else plan.prior_error,
        prior_error_deg=math.nan if plan.prior_error_deg is None else plan.prior_error_deg,
        working_set=renderer.largest, working_set_selections=renderer.selections,
        renders=ctx.scorer.renders + sum(p.renders for p in polish), seconds=seconds)
    return res
