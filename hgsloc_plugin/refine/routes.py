"""The routes from a coarse pose to a candidate: the gradient route (Levenberg-Marquardt alone, coarse to fine),
the search route (best-first lattice search over step levels, then the polish), the wide gradient route (the polish
from the prior started at a very small size) and the wide search route (lattice levels of wide steps at that size,
then the polish coarse to fine from there).

Each route takes the query's :class:`QueryContext` and returns a :class:`Candidate`: the pose the acceptance
rule (``trust.judge``) then judges, with the costs and the effort that led to it.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from ..core.camera import Camera
from ..core.pose import Pose
from ..render import RendererLike
from ..render.lod import coarse_lod
from .config import RefineConfig
from .plan import Plan
from .polish import FINAL, FINE_LINE_SEARCH, LINE_SEARCH, STAGE, STAGE_STEP_PX, PolishStats, polish
from .scorer import Scorer
from .search import LatticeSpace, LevelStats, PaperSpace, best_first

#: the wide search polishes its lattice's best pose and up to this many minus one more distinct low ones
#: (``distinct_minima``), and returns the polished pose of lowest cost at the judging size
WIDE_HYPOTHESES = 3
#: the wide search's hypotheses lie more than this many of its coarsest steps (``Tuning.wide_step_pixels[0]``) apart
WIDE_SEPARATION_STEPS = 2.0
#: two polished hypotheses agree when they end this close (pixels of image motion at the judging size): within the
#: resolution at which a polish stage hands over to a finer one, so two polishes from starts over 32 px apart that
#: meet there found one basin whose minimum the polish resolves (``Candidate.agreeing``)
WIDE_AGREEMENT_PX = STAGE_STEP_PX


@dataclass
class QueryContext:
    """One query as the routes see it: settings, plan, the renderer (whole map or working set), the scorer (its
    render count spans every route), the query image [H, W, 3] float32 at its own size and the refiner's stage
    trace hook (``Refiner.on_stage``)."""

    config: RefineConfig
    plan: Plan
    renderer: RendererLike
    scorer: Scorer
    image: np.ndarray
    name: str | None = None
    on_stage: Callable[[str, float], None] | None = None

    @contextlib.contextmanager
    def timed(self, stage: str) -> Iterator[None]:
        """Reports the seconds inside to ``on_stage`` as ``stage`` (nothing when no hook is set)."""
        if self.on_stage is None:
            yield
            return
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.on_stage(stage, time.perf_counter() - t0)

    @property
    def judge_cam(self) -> Camera:
        """Where the rule judges a candidate: at the polish's size when it runs (a pose polished at the query's own
        pixels is not the minimum of the 200 px cost, whose one-pixel moves may then descend)."""
        return self.plan.cam_polish if self.config.polishes else self.plan.cam_final


@dataclass
class Candidate:
    """A route's result: its pose, its cost and the coarse pose's cost (at ``judge_cam`` once judged: the rule,
    ``trust.judge``, scores both with its own poses in one batch; before, the search's running costs), the search's
    pose after its pyramid levels (the coarse pose when no search ran), the route's effort, and for the wide search
    how many of its other polished hypotheses ended within ``WIDE_AGREEMENT_PX`` of its pose (``agreeing``)."""

    route: str
    pose: Pose
    cost: float
    cost_initial: float
    after_coarse: Pose
    polish: list[PolishStats] = field(default_factory=list)
    levels: list[LevelStats] = field(default_factory=list)
    history: list[float] = field(default_factory=list)
    expansions: int = 0
    agreeing: int = 0


def gradient_route(ctx: QueryContext) -> Candidate:
    """The polish alone from the coarse pose, coarse to fine over the pyramid, final and polish sizes."""
    return _route(ctx, search=False)


def search_route(ctx: QueryContext) -> Candidate:
    """The best-first lattice search over the step levels from the coarse pose, then the polish at its size."""
    return _route(ctx, search=True)


def _route(ctx: QueryContext, search: bool) -> Candidate:
    cfg, plan, scorer, coarse = ctx.config, ctx.plan, ctx.scorer, ctx.plan.coarse_pose
    cost_initial = math.nan
    if search:  # the search starts from the coarse pose's cost at the final size
        scorer.set_query(plan.cam_final, ctx.image, renderer=ctx.renderer)
        cost_initial = float(scorer([coarse])[0])
    cand = Candidate("search" if search else "gradient", coarse, cost_initial, cost_initial, coarse)
    if search:
        _search_levels(ctx, cand)
    if cfg.polishes:
        cams = [plan.cam_polish] if search else [plan.cam_coarse, plan.cam_final, plan.cam_polish]
        cand.pose = _polish(ctx, cand, cams, near=search)
    _scorer_to_judge_size(ctx)
    return cand


def wide_gradient_route(ctx: QueryContext) -> Candidate:
    """The polish from the coarse pose started at the wide search's size ``plan.cam_wide`` (``Tuning.wide_max_side``),
    then coarse to fine over the pyramid, final and polish sizes: the second hypothesis for a gradient route that
    travelled beyond the cs window's reach (``refiner._beyond_reach``). At 32 px a texture of a few pixels' period at
    the final size (stripes, tiles, shelves) is blurred away, so the first stage follows the view's coarse structure
    instead of the nearest period (``../shared/data/cases/room_stripes``). Needs ``config.polishes``."""
    coarse = ctx.plan.coarse_pose
    cand = Candidate("wide gradient", coarse, math.nan, math.nan, coarse)
    cand.pose = _polish_from_wide_size(ctx, cand)
    _scorer_to_judge_size(ctx)
    return cand


def _polish_from_wide_size(ctx: QueryContext, cand: Candidate) -> Pose:
    """The polish from ``cand.pose`` over the wide, pyramid, final and polish sizes (``_polish``, the first stage
    not near its minimum)."""
    plan = ctx.plan
    return _polish(ctx, cand, [plan.cam_wide, plan.cam_coarse, plan.cam_final, plan.cam_polish], near=False)


def _scorer_to_judge_size(ctx: QueryContext) -> None:
    """Leave the scorer at ``judge_cam`` on the query's renderer, where the rule scores the candidate (its costs
    so far, at that size and renderer, stay cached)."""
    scorer = ctx.scorer
    if scorer.camera != ctx.judge_cam or scorer.renderer is not ctx.renderer:
        scorer.set_query(ctx.judge_cam, ctx.image, renderer=ctx.renderer)


def wide_search_route(ctx: QueryContext) -> Candidate:
    """The wide search, for priors tens of pixels of image motion off (after the search's pose is refused):
    best-first lattice levels of the plan's steps (``Tuning.wide_step_pixels``) with pattern moves, scored at
    the small ``plan.cam_wide`` (``wide_max_side``) where the cost still falls towards the truth, then the polish
    coarse to fine from that size over the wide, pyramid, final and polish sizes, from the lattice's best pose and
    from up to ``WIDE_HYPOTHESES - 1`` more distinct low ones (:func:`distinct_minima`): the polished pose of lowest
    cost at the judging size is the candidate. Needs ``config.polishes``."""
    cfg, plan, scorer, coarse = ctx.config, ctx.plan, ctx.scorer, ctx.plan.coarse_pose
    scorer.set_query(plan.cam_wide, ctx.image, renderer=ctx.renderer)
    best_pose, best_cost = coarse, float(scorer([coarse])[0])
    cand = Candidate("wide search", coarse, math.nan, math.nan, coarse)
    scored = [(coarse, best_cost)]
    remaining = cfg.tuning.max_expansions
    for step in plan.levels:
        if remaining <= 0:
            break
        best_pose, best_cost, used = _level(ctx, cand, best_pose, best_cost, step, plan.cam_wide,
                                            min(cfg.tuning.max_expansions_per_level, remaining), pattern=True,
                                            scored=scored)
        remaining -= used
    separation = WIDE_SEPARATION_STEPS * cfg.tuning.wide_step_pixels[0]
    hypotheses = []
    for start in distinct_minima(scored, plan, WIDE_HYPOTHESES, separation):
        hyp = Candidate(cand.route, start, math.nan, math.nan, start)
        hyp.pose = _polish_from_wide_size(ctx, hyp)
        hypotheses.append(hyp)
    _scorer_to_judge_size(ctx)
    pick = hypotheses[int(np.argmin(scorer([h.pose for h in hypotheses])))] if len(hypotheses) > 1 else hypotheses[0]
    cand.pose, cand.after_coarse = pick.pose, pick.after_coarse
    cand.agreeing = sum(plan.pixels_apart(h.pose, pick.pose, ctx.judge_cam) <= WIDE_AGREEMENT_PX
                        for h in hypotheses if h is not pick)
    # the picked hypothesis's stages last: the rule reads its last stage's model (``trust.last_stage_at``)
    cand.polish = [s for h in hypotheses if h is not pick for s in h.polish] + pick.polish
    return cand


def distinct_minima(scored: list[tuple[Pose, float]], plan: Plan, n: int, pixels: float) -> list[Pose]:
    """Up to ``n`` poses of ``scored`` ((pose, cost) pairs), lowest cost first, each more than ``pixels`` of image
    motion at the final size (``Plan.pixels_apart``) from every one taken before it; ties in cost keep ``scored``'s
    order."""
    order = sorted(range(len(scored)), key=lambda i: scored[i][1])
    taken: list[Pose] = []
    for i in order:
        pose = scored[i][0]
        if len(taken) >= n:
            break
        if all(plan.pixels_apart(pose, t) > pixels for t in taken):
            taken.append(pose)
    return taken


def _search_levels(ctx: QueryContext, cand: Candidate) -> None:
    """Run the step levels coarse to fine from ``cand`` (the coarse pose at its cost); leaves in ``cand`` the best
    pose, its cost at the final size, the best pose after the pyramid levels and the levels' effort."""
    cfg, plan, scorer = ctx.config, ctx.plan, ctx.scorer
    best_pose, best_cost, best_cam = cand.pose, cand.cost, plan.cam_final
    remaining = cfg.tuning.max_expansions
    exact, lod = scorer.renderer, None
    for li, step in enumerate(plan.levels):
        if remaining <= 0:
            break
        is_coarse = li < cfg.tuning.coarse_levels and li < len(plan.levels) - 1
        cam_l = plan.cam_coarse if is_coarse else plan.cam_final
        if is_coarse and lod is None and cfg.tuning.coarse_lod_pixels is not None and exact.full is not exact:
            lod = coarse_lod(exact.full, plan.cam_coarse, plan.coarse_pose, plan.max_shift, plan.max_rotation_deg,
                             cfg.tuning.coarse_lod_pixels)
        want = lod if is_coarse and lod is not None else exact
        if cam_l != best_cam or want is not scorer.renderer:
            scorer.set_query(cam_l, ctx.image, renderer=want)
            best_cost = float(scorer([best_pose])[0])
            best_cam = cam_l
        best_pose, best_cost, used = _level(ctx, cand, best_pose, best_cost, step, cam_l,
                                            min(cfg.tuning.max_expansions_per_level, remaining),
                                            pattern=cfg.tuning.pattern_moves and cfg.tuning.neighbourhood == "lattice")
        remaining -= used
        if is_coarse:
            cand.after_coarse = best_pose
    if best_cam != plan.cam_final or scorer.renderer is not exact:
        scorer.set_query(plan.cam_final, ctx.image, renderer=exact)
        best_cost = float(scorer([best_pose])[0])
    cand.pose, cand.cost = best_pose, best_cost


def _level(ctx: QueryContext, cand: Candidate, pose: Pose, cost: float, step: tuple[float, float], cam: Camera,
           budget: int, pattern: bool, scored: list[tuple[Pose, float]] | None = None) -> tuple[Pose, float, int]:
    """One best-first level of ``step`` (degrees, scene units) from ``pose`` at its ``cost``, scored at ``cam``
    (the scorer's current size), in ``config.tuning.neighbourhood``; adds its effort to ``cand`` and, given
    ``scored``, every pose it scored with its cost (its start excluded). Returns the best pose, its cost and the
    expansions used."""
    cfg, plan = ctx.config, ctx.plan
    s_rot, s_t = step
    if cfg.tuning.neighbourhood == "paper":
        space = PaperSpace(pose, s_rot, s_t)
    else:
        space = LatticeSpace(pose, math.radians(s_rot), s_t, plan.depth if cfg.tuning.pivot else 0.0)
    with ctx.timed(f"search {cam.width}x{cam.height}"):
        lr = best_first(space, cost, ctx.scorer, plan.allows, budget=budget, patience=cfg.tuning.patience,
                        weight=cfg.tuning.heuristic_weight, depth_cost=cfg.tuning.depth_cost, pattern=pattern)
    cand.expansions += lr.expansions
    cand.history.extend(lr.history)
    if scored is not None:
        origin = (0,) * space.dim
        scored.extend((space.pose(k), c) for k, c in lr.costs.items() if k != origin and math.isfinite(c))
    cand.levels.append(LevelStats(s_rot, s_t, cam.width, cam.height, lr.expansions, lr.renders, lr.best_cost,
                                  lr.stopped))
    return space.pose(lr.best_key), lr.best_cost, lr.expansions


def _polish(ctx: QueryContext, cand: Candidate, cams: list[Camera], near: bool) -> Pose:
    """Levenberg-Marquardt on the cs cost (``refine/polish.py``) from ``cand.pose``, one stage per camera of
    ``cams`` (coarse to fine; repeated sizes run once). A stage that starts near its minimum (after a coarser
    stage, or the first when ``near``: after the search) scores the shorter line search ``FINE_LINE_SEARCH``.
    Appends to ``cand.polish``."""
    cfg, plan = ctx.config, ctx.plan
    cams = list(dict.fromkeys(cams))
    pose = cand.pose
    for i, cam in enumerate(cams):
        q = ctx.scorer.window_query(cam, ctx.image)
        last = i == len(cams) - 1  # a stage before a finer one stops at a coarser step: the next goes on
        with ctx.timed(f"polish {cam.width}x{cam.height}"):
            pose, stats = polish(ctx.renderer, cam, q, pose, depth=plan.depth,
                                 iterations=cfg.tuning.polish_iterations, allowed=plan.allows,
                                 background=cfg.background, mask_alpha=cfg.tuning.mask_alpha,
                                 converged=FINAL if last else STAGE,
                                 line_search=FINE_LINE_SEARCH if near or i > 0 else LINE_SEARCH)
        cand.polish.append(stats)
    return pose
