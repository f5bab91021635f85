"""RefineConfig: what a user sets for the pose search (its inner settings in ``Tuning``), and the named presets."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

from ..core.costs import METRICS as _COSTS
from ..core.costs import SEARCH_METRICS as METRICS
from .uncertainty import FLOOR_DEG, FLOOR_DEPTH

#: which routes a query runs (``RefineConfig.routes``)
ROUTES = ("gradient_first", "search", "gradient", "lattice")


@dataclass(frozen=True, kw_only=True)
class Tuning:
    """The search's and the polish's inner settings: budgets, step sizes, pyramid, working set. A user rarely
    touches them; each default's reason is in ``benchmarks/defaults.md``. Sizes are pixels of the longer side.

    Attributes:
        neighbourhood: "lattice" (12 moves: +-step about and along each camera axis) or "paper" (14 moves: +-step
            on each raw q, t component, as the official code).
        levels: explicit (rotation step, translation step) per level, coarse to fine; empty: from ``level_pixels``.
        level_pixels: image motion (pixels at the final scoring size) of each automatic level's step; None:
            (4, 2, 1) with the polish, else (4, 2, 1, 0.5, 0.25, 0.125).
        max_expansions_per_level / max_expansions: expansion budgets per level and per query.
        patience: expansions without a new best before a level stops (0: never).
        pivot: lattice rotations turn about a point on the optical axis at the median depth (else the centre).
        pattern_moves: also score the node that repeats the move which reached the expanded node.
        heuristic_weight / depth_cost: node priority ``depth_cost * g + heuristic_weight * h``.
        coarse_levels / coarse_scale / coarse_min_side: the first ``coarse_levels`` levels score at
            ``coarse_scale`` times the scoring size, at least ``coarse_min_side``.
        trust_steps: the automatic trust region, in coarsest steps.
        working_set / working_set_min / working_set_pixels: render from the Gaussians seen near the poses scored
            (``working_set.WorkingSet``; same images) on maps of at least ``working_set_min`` Gaussians, selected
            for a region of ``working_set_pixels`` of image motion.
        coarse_lod_pixels: the pyramid levels render a level of detail merging Gaussians of at most this many
            pixels (``lod.py``; approximate; with a working set only); None: the exact map.
        lod_pixels: every render of a query draws from a cut of the map's level-of-detail hierarchy
            (``render/hierarchy.py``, built once per map and cached), one per image size, merging cells of up to
            this many pixels at that size; approximate (on real photos 1 px moved poses 0.002 % of the depth, 2 px
            0.02 %: ``benchmarks/map_scale.md``); with a working set only; None: the exact map.
        antialias: every scoring size below the query image's (the wide search's excepted) renders as the image
            reduced to it (``Camera.downsample``: the 3DGS dilation scaled, the reduction's filter with its opacity
            compensation; ``benchmarks/defaults.md``); off: every size renders as 3DGS renders at its training size.
        polish_iterations: the polish's derivative passes at most.
        wide_step_pixels: image motion (pixels at the final scoring size) of the wide search's lattice levels,
            run only when the search's pose is refused (priors 30-100 px of image motion off), with the automatic
            trust region ``trust_steps`` times the first of them (not run when the query's own trust region is no
            larger than the search's: nothing wider to search); needs the polish; (): off.
        wide_max_side: the wide search's scoring size: its lattice levels and the first stage of its polish score
            there, where the cost falls towards the truth from tens of pixels away.
        same_minimum_pixels: no wide search when the gradient route and the search were both refused, neither at
            the trust region's edge, at poses this close (image motion at the final size): two explorations that
            end in one minimum found the map's own minimum near the prior (its floor), not a far prior's plateau
            (``benchmarks/basin.md``); 0: the wide search after every refused search.
        mask_alpha: ignore pixels whose rendered alpha is below this.
        map_floor_depth / map_floor_deg: the map's own error at a view, as 3-D standard deviations (camera centre
            as a fraction of the query's median depth, rotation in degrees), added to every polished pose's
            covariance: what no image statistic sees (``refine/uncertainty.py``). Measure it on views with known
            poses (``hgsloc check --measure-floor``, :func:`~hgsloc_plugin.evaluation.floor.map_floor`); the
            default is a good real map's (0.3 % / 0.1 deg).
        map_cost_bound: a refined pose whose cs cost at the judging size is above this is refused ("cost above
            the map's level"); ``hgsloc check --measure-floor`` prints it with the floor (the 99.9 % prediction bound
            of the costs right answers reach at views with known poses, ``evaluation/floor.py``); None: no bound.
        paper_step_q / paper_step_t: the "paper" neighbourhood's raw-component steps.
    """

    neighbourhood: str = "lattice"
    levels: tuple[tuple[float, float], ...] = ()
    level_pixels: tuple[float, ...] | None = None
    max_expansions_per_level: int = 30
    max_expansions: int = 180
    patience: int = 2
    pivot: bool = True
    pattern_moves: bool = False
    heuristic_weight: float = 1.0
    depth_cost: float = 0.0
    coarse_scale: float = 0.5
    coarse_levels: int = 2
    coarse_min_side: int = 80
    trust_steps: float = 8.0
    working_set: bool = True
    working_set_min: int = 100_000
    working_set_pixels: float = 8.0
    coarse_lod_pixels: float | None = None
    lod_pixels: float | None = None
    antialias: bool = True
    polish_iterations: int = 16
    wide_step_pixels: tuple[float, ...] = (16.0, 8.0)
    wide_max_side: int = 32
    same_minimum_pixels: float = 1.0
    mask_alpha: float = 0.0
    map_floor_depth: float = FLOOR_DEPTH
    map_floor_deg: float = FLOOR_DEG
    map_cost_bound: float | None = None
    paper_step_q: float = 1e-4
    paper_step_t: float = 1e-4

    def __post_init__(self) -> None:
        if not (self.working_set_pixels > 0 and math.isfinite(self.working_set_pixels)):
            raise ValueError(f"working_set_pixels must be a positive number, got {self.working_set_pixels!r}")
        if self.coarse_lod_pixels is not None and not (self.coarse_lod_pixels > 0
                                                       and math.isfinite(self.coarse_lod_pixels)):
            raise ValueError(f"coarse_lod_pixels must be a positive number or None, got {self.coarse_lod_pixels!r}")
        if self.lod_pixels is not None and not (self.lod_pixels > 0 and math.isfinite(self.lod_pixels)):
            raise ValueError(f"lod_pixels must be a positive number or None, got {self.lod_pixels!r}")
        if not self.trust_steps > 0:
            raise ValueError(f"trust_steps must be > 0, got {self.trust_steps}")
        if self.neighbourhood not in ("lattice", "paper"):
            raise ValueError(f"neighbourhood must be 'lattice' or 'paper', got {self.neighbourhood!r}")
        if self.max_expansions < 0 or self.max_expansions_per_level < 0 or self.patience < 0:
            raise ValueError("expansion budgets and patience must be >= 0")
        if self.polish_iterations < 1:
            raise ValueError(f"polish_iterations must be >= 1, got {self.polish_iterations}")
        if not (0 < self.coarse_scale <= 1):
            raise ValueError(f"coarse_scale must be in (0, 1], got {self.coarse_scale}")
        for lv in self.levels:
            if len(lv) != 2 or lv[0] < 0 or lv[1] < 0 or (lv[0] == 0 and lv[1] == 0):
                raise ValueError(f"each level must be (rotation_deg >= 0, translation >= 0), got {lv!r}")
        object.__setattr__(self, "levels", tuple(tuple(float(x) for x in lv) for lv in self.levels))
        if self.level_pixels is not None:
            object.__setattr__(self, "level_pixels", tuple(float(x) for x in self.level_pixels))
        if not all(x > 0 and math.isfinite(x) for x in self.wide_step_pixels):
            raise ValueError(f"wide_step_pixels must be positive numbers, got {self.wide_step_pixels!r}")
        object.__setattr__(self, "wide_step_pixels", tuple(float(x) for x in self.wide_step_pixels))
        if not self.wide_max_side >= 16:
            raise ValueError(f"wide_max_side must be >= 16, got {self.wide_max_side!r}")
        for name in ("map_floor_depth", "map_floor_deg"):
            if not (getattr(self, name) >= 0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"{name} must be a number >= 0, got {getattr(self, name)!r}")
        if self.map_cost_bound is not None and not (self.map_cost_bound > 0 and math.isfinite(self.map_cost_bound)):
            raise ValueError(f"map_cost_bound must be a positive number or None, got {self.map_cost_bound!r}")
        if not (self.same_minimum_pixels >= 0 and math.isfinite(self.same_minimum_pixels)):
            raise ValueError(f"same_minimum_pixels must be a number >= 0, got {self.same_minimum_pixels!r}")


class RouteChoice(NamedTuple):
    """Which routes a query runs, in order (``RefineConfig.route_choice``).

    Attributes:
        gradient_first: the gradient route (the polish from the prior) first; the rest only when it is refused.
        main: "search" (lattice search, then the polish when ``polish``) or "gradient" (the polish alone).
        polish: whether the polish runs (the routes allow it, the metric is cs, the neighbourhood the lattice).
        wide: the wide search after a refused search.
    """

    gradient_first: bool
    main: str
    polish: bool
    wide: bool


@dataclass(frozen=True, kw_only=True)
class RefineConfig:
    """Settings of :class:`~hgsloc_plugin.HGSLocPlugin`: what a user sets. Lengths are in scene units, angles in
    degrees, image sizes in pixels of the longer side. Why each default is what it is: ``benchmarks/defaults.md``.

    Attributes:
        routes: "gradient_first" (default: the polish from the prior; the lattice search, then the wide search,
            when its pose is refused), "search" (always the search and its polish), "gradient" (the polish only)
            or "lattice" (the search only, no polish: the paper's scheme).
        metric: the cost (``costs.METRICS``; lower is better): "cs" (default), "ssim", "sad", "psnr", "ncc" or
            "affine"; the polish runs on cs only.
        score_max_side: the search's scoring size (its pyramid levels score smaller: ``Tuning.coarse_scale``).
        polish_max_side: the polish's largest size.
        max_shift / max_rotation_deg: the trust region around the coarse pose; None: ``Tuning.trust_steps``
            coarsest steps. A query's ``QueryPrior`` overrides them.
        prior_error / prior_error_deg: the coarse poses' expected (median) error; None: unknown. Given, an
            accepted pose is fused with its prior (``uncertainty.fuse_with_prior``) and the prior is kept when the
            fusion's cost is not lower ("prior more precise").
        acceptance: "trust" (the rule of ``refine/trust.py``) or "cost" (any lower cost, the paper's rule).
        background: RGB behind the Gaussians (the map's training background).
        resize_query: resize a query whose size differs from its camera's instead of raising.
        tuning: the inner settings (:class:`Tuning`).
    """

    routes: str = "gradient_first"
    metric: str = "cs"
    score_max_side: int = 200
    polish_max_side: int = 320
    max_shift: float | None = None
    max_rotation_deg: float | None = None
    prior_error: float | None = None
    prior_error_deg: float | None = None
    acceptance: str = "trust"
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    resize_query: bool = False
    tuning: Tuning = Tuning()

    def __post_init__(self) -> None:
        if self.routes not in ROUTES:
            raise ValueError(f"routes must be one of {ROUTES}, got {self.routes!r}")
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.acceptance not in ("trust", "cost"):
            raise ValueError(f"acceptance must be 'trust' or 'cost', got {self.acceptance!r}")
        for name in ("max_shift", "max_rotation_deg", "prior_error", "prior_error_deg"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number or None, got {v!r}")
        if not isinstance(self.tuning, Tuning):
            raise TypeError(f"tuning must be a Tuning, got {type(self.tuning).__name__}")
        if self.routes == "gradient" and not self.polishes:
            raise ValueError("routes='gradient' (gradient only: the polish alone) needs metric='cs' and the lattice "
                             "neighbourhood")
        if self.polish_max_side < 8:
            raise ValueError(f"polish_max_side must be >= 8, got {self.polish_max_side}")
        if self.score_max_side < 8:
            raise ValueError(f"score_max_side must be >= 8, got {self.score_max_side}")
        object.__setattr__(self, "background", tuple(float(x) for x in self.background))

    @staticmethod
    def preset(name: str, **overrides) -> RefineConfig:
        """A named preset ("default", "fast", "accurate", "gradient", "search", "paper"), with overrides of
        its fields or its :class:`Tuning`'s (``RefineConfig.preset("search", max_expansions=60)``)."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
        return PRESETS[name].replace(**overrides)

    @property
    def polishes(self) -> bool:
        """Whether the polish runs (the routes include it, the metric is cs and the neighbourhood the lattice)."""
        return (self.routes != "lattice" and _COSTS[self.metric].polish
                and self.tuning.neighbourhood == "lattice")

    def route_choice(self) -> RouteChoice:
        """The routes a query runs: the gradient route first only with the polish and the trust rule (the cost
        rule would accept its every descent); the wide search after a refused search, with the polish, on
        automatic levels."""
        polish = self.polishes
        main = "gradient" if self.routes == "gradient" else "search"
        return RouteChoice(
            gradient_first=self.routes == "gradient_first" and polish and self.acceptance == "trust",
            main=main, polish=polish,
            wide=bool(self.tuning.wide_step_pixels) and main == "search" and polish and not self.tuning.levels)

    @property
    def step_pixels(self) -> tuple[float, ...]:
        """``Tuning.level_pixels``, or its default when None."""
        if self.tuning.level_pixels is not None:
            return self.tuning.level_pixels
        return (4.0, 2.0, 1.0) if self.polishes else (4.0, 2.0, 1.0, 0.5, 0.25, 0.125)

    def replace(self, **changes) -> RefineConfig:
        """A copy with ``changes`` to its fields or to its :class:`Tuning`'s (named as they are there)."""
        tuning = {k: changes.pop(k) for k in list(changes) if k in _TUNING_FIELDS}
        unknown = sorted(set(changes) - _CONFIG_FIELDS)
        if unknown:
            raise TypeError(f"unknown RefineConfig settings {unknown}: fields are {sorted(_CONFIG_FIELDS)}, "
                            f"tuning fields {sorted(_TUNING_FIELDS)}" + _RENAMED_HINT)
        if tuning:
            changes["tuning"] = dataclasses.replace(changes.get("tuning", self.tuning), **tuning)
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The settings as plain data (a report's ``config``; its digest is a run's resume fingerprint). Tuning fields
        added after reports were first written (``ADDED_UNSET``) are left out while unset, so a run of the same
        settings made before them still resumes."""
        out = dataclasses.asdict(self)
        for name, unset in ADDED_UNSET.items():
            if out["tuning"].get(name, unset) == unset:
                out["tuning"].pop(name, None)
        return out


#: Tuning fields added after reports were first written, with the value that leaves them unset (``to_dict``)
ADDED_UNSET = {"map_cost_bound": None}
_CONFIG_FIELDS = {f.name for f in dataclasses.fields(RefineConfig)}
_TUNING_FIELDS = {f.name for f in dataclasses.fields(Tuning)}
_RENAMED_HINT = (" (routes replaces polish / search / gradient_first: polish=False is routes='lattice', "
                 "search=False routes='gradient', gradient_first=False routes='search')")


#: the presets in a command line's help (``hgsloc refine --config``, the HLoc step, the examples)
PRESET_HELP = ("preset: default (gradient first, the search when it is refused), fast (scored and polished at 120 "
               "px: faster, coarser), accurate (polished up to 480 px, for large queries), search (always search), "
               "gradient, paper; figures: benchmarks/presets.md")

PRESETS: dict[str, RefineConfig] = {
    "default": RefineConfig(),
    # Levenberg-Marquardt from the coarse pose, no lattice search (where each part is needed: benchmarks/).
    "gradient": RefineConfig(routes="gradient"),
    # Always the lattice search + polish (no gradient-first route).
    "search": RefineConfig(routes="search"),
    # Scoring and polish at 120 px, smaller search budgets: 1.5-1.8x faster than the default on 198 px photos,
    # 2.8-4.7x on 320-640 px queries; its error 1.7x the default's on the sharp real map, 4-12x on the synthetic
    # room's 320-640 px queries (0.45-0.87 cm against 0.04-0.21: benchmarks/presets.md).
    "fast": RefineConfig(score_max_side=120, polish_max_side=120,
                         tuning=Tuning(max_expansions_per_level=15, max_expansions=60, polish_iterations=4)),
    # Polish up to 480 px (the default: 320), larger search budgets: on 640x480 queries 4x less error for 1.6x
    # the time; as the default on smaller ones (benchmarks/presets.md; at 640 px the rule refused there).
    "accurate": RefineConfig(polish_max_side=480, tuning=Tuning(max_expansions_per_level=40, max_expansions=280,
                                                                patience=3)),
    # Emulation of the official scheme: raw-component steps, one fixed level, f = g + h, 399 expansions,
    # L1 cost, no early stop.
    "paper": RefineConfig(routes="lattice", metric="sad", max_shift=0.5, max_rotation_deg=5.0, acceptance="cost",
                          tuning=Tuning(neighbourhood="paper", max_expansions_per_level=399, max_expansions=399,
                                        patience=0, heuristic_weight=1.0, depth_cost=1.0, coarse_scale=1.0)),
}
