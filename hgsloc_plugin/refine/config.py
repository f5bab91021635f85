"""RefineConfig: every setting of the pose search, with named presets stored as data."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..core.costs import METRICS as _COSTS
from ..core.costs import SEARCH_METRICS as METRICS


@dataclass(frozen=True, kw_only=True)
class RefineConfig:
    """Settings of :class:`~hgsloc_plugin.HGSLocPlugin`. Lengths are in scene units, angles in degrees, image
    sizes in pixels of the longer side. Why each default is what it is: ``benchmarks/defaults.md``.

    Attributes:
        metric: the cost (``costs.METRICS``; lower is better): "cs" (default), "ssim", "sad", "psnr", "ncc" or
            "affine".
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
        score_max_side: the fine levels' scoring size; the first ``coarse_levels`` levels score at
            ``coarse_scale`` times it, at least ``coarse_min_side``.
        max_shift / max_rotation_deg: the trust region around the coarse pose; None: ``trust_steps`` coarsest
            steps. A query's ``QueryPrior`` overrides them.
        prior_error / prior_error_deg: the coarse poses' expected (median) error; None: unknown. Given, an
            accepted pose is fused with its prior (``uncertainty.fuse_with_prior``) and the prior is kept when the
            fusion's cost is not lower ("prior more precise").
        acceptance: "trust" (the rule of ``refine/trust.py``) or "cost" (any lower cost, the paper's rule).
        working_set / working_set_min / working_set_pixels: render from the Gaussians seen near the poses scored
            (``working_set.WorkingSet``; same images) on maps of at least ``working_set_min`` Gaussians, selected
            for a region of ``working_set_pixels`` of image motion.
        coarse_lod_pixels: the pyramid levels render a level of detail merging Gaussians of at most this many
            pixels (``lod.py``; approximate; with a working set only); None: the exact map.
        polish: Levenberg-Marquardt on the cs cost after the search (``refine/polish.py``), at
            ``polish_max_side`` with at most ``polish_iterations`` derivative passes; cs metric only.
        gradient_first: try the gradient route (the polish alone) first; search only when its pose is refused.
        search: run the lattice search; False with ``polish``: gradient only.
        wide_step_pixels: image motion (pixels at the final scoring size) of the wide search's lattice levels,
            run only when the search's pose is refused (priors 30-100 px of image motion off), with the automatic
            trust region ``trust_steps`` times the first of them (not run when the query's own trust region is no
            larger than the search's: nothing wider to search); needs the polish; (): off.
        wide_max_side: the wide search's scoring size (longest side, pixels): its lattice levels and the first
            stage of its polish score there, where the cost falls towards the truth from tens of pixels away.
        same_minimum_pixels: no wide search when the gradient route and the search were both refused, neither at
            the trust region's edge, at poses this close (image motion at the final size): two explorations that
            end in one minimum found the map's own minimum near the prior (its floor), not a far prior's plateau
            (``benchmarks/basin.md``); 0: the wide search after every refused search.
        mask_alpha: ignore pixels whose rendered alpha is below this.
        background: RGB behind the Gaussians (the map's training background).
        resize_query: resize a query whose size differs from its camera's instead of raising.
        paper_step_q / paper_step_t: the "paper" neighbourhood's raw-component steps.
    """

    metric: str = "cs"
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
    score_max_side: int = 200
    coarse_scale: float = 0.5
    coarse_levels: int = 2
    coarse_min_side: int = 80
    max_shift: float | None = None
    max_rotation_deg: float | None = None
    trust_steps: float = 8.0
    prior_error: float | None = None
    prior_error_deg: float | None = None
    acceptance: str = "trust"
    working_set: bool = True
    working_set_min: int = 100_000
    working_set_pixels: float = 8.0
    coarse_lod_pixels: float | None = None
    polish: bool = True
    gradient_first: bool = True
    polish_iterations: int = 16
    polish_max_side: int = 320
    search: bool = True
    wide_step_pixels: tuple[float, ...] = (16.0, 8.0)
    wide_max_side: int = 32
    same_minimum_pixels: float = 1.0
    mask_alpha: float = 0.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    resize_query: bool = False
    paper_step_q: float = 1e-4
    paper_step_t: float = 1e-4

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.acceptance not in ("trust", "cost"):
            raise ValueError(f"acceptance must be 'trust' or 'cost', got {self.acceptance!r}")
        for name in ("max_shift", "max_rotation_deg", "prior_error", "prior_error_deg"):
            v = getattr(self, name)
            if v is not None and not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number or None, got {v!r}")
        if not (self.working_set_pixels > 0 and math.isfinite(self.working_set_pixels)):
            raise ValueError(f"working_set_pixels must be a positive number, got {self.working_set_pixels!r}")
        if self.coarse_lod_pixels is not None and not (self.coarse_lod_pixels > 0
                                                       and math.isfinite(self.coarse_lod_pixels)):
            raise ValueError(f"coarse_lod_pixels must be a positive number or None, got {self.coarse_lod_pixels!r}")
        if not self.trust_steps > 0:
            raise ValueError(f"trust_steps must be > 0, got {self.trust_steps}")
        if self.neighbourhood not in ("lattice", "paper"):
            raise ValueError(f"neighbourhood must be 'lattice' or 'paper', got {self.neighbourhood!r}")
        if self.max_expansions < 0 or self.max_expansions_per_level < 0 or self.patience < 0:
            raise ValueError("expansion budgets and patience must be >= 0")
        if self.polish_iterations < 1 or self.polish_max_side < 8:
            raise ValueError("polish_iterations must be >= 1 and polish_max_side >= 8")
        if not self.search and not self.polishes:
            raise ValueError("search=False (gradient only) needs polish=True, metric='cs' and the lattice "
                             "neighbourhood")
        if self.score_max_side < 8:
            raise ValueError(f"score_max_side must be >= 8, got {self.score_max_side}")
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
        if not (self.same_minimum_pixels >= 0 and math.isfinite(self.same_minimum_pixels)):
            raise ValueError(f"same_minimum_pixels must be a number >= 0, got {self.same_minimum_pixels!r}")
        object.__setattr__(self, "background", tuple(float(x) for x in self.background))

    @staticmethod
    def preset(name: str, **overrides) -> RefineConfig:
        """A named preset ("default", "fast", "accurate", "gradient", "search", "paper"), with field overrides."""
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
        return dataclasses.replace(PRESETS[name], **overrides)

    @property
    def polishes(self) -> bool:
        """Whether the polish runs (it is on, the metric is cs and the neighbourhood the lattice)."""
        return self.polish and _COSTS[self.metric].polish and self.neighbourhood == "lattice"

    @property
    def step_pixels(self) -> tuple[float, ...]:
        """``level_pixels``, or its default when None."""
        if self.level_pixels is not None:
            return self.level_pixels
        return (4.0, 2.0, 1.0) if self.polishes else (4.0, 2.0, 1.0, 0.5, 0.25, 0.125)

    def replace(self, **changes) -> RefineConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: the presets in a command line's help (``hgsloc refine --config``, the HLoc step, the examples)
PRESET_HELP = ("preset: default (gradient first, the search when it is refused), fast (scored and polished at 120 "
               "px: faster, coarser), accurate (polished up to 480 px, for large queries), search (always search), "
               "gradient, paper; figures: benchmarks/presets.md")

PRESETS: dict[str, RefineConfig] = {
    "default": RefineConfig(),
    # Levenberg-Marquardt from the coarse pose, no lattice search (where each part is needed: benchmarks/).
    "gradient": RefineConfig(search=False),
    # Always the lattice search + polish (no gradient-first route).
    "search": RefineConfig(gradient_first=False),
    # Scoring and polish at 120 px, smaller search budgets: 1.5-1.8x faster than the default on 198 px photos,
    # 2.8-4.7x on 320-640 px queries; its error 1.7x the default's on the sharp real map, 4-12x on the synthetic
    # room's 320-640 px queries (0.45-0.87 cm against 0.04-0.21: benchmarks/presets.md).
    "fast": RefineConfig(max_expansions_per_level=15, max_expansions=60, score_max_side=120, polish_iterations=4,
                         polish_max_side=120),
    # Polish up to 480 px (the default: 320), larger search budgets: on 640x480 queries 4x less error for 1.6x
    # the time; as the default on smaller ones (benchmarks/presets.md; at 640 px the rule refused there).
    "accurate": RefineConfig(max_expansions_per_level=40, max_expansions=280, patience=3, polish_max_side=480),
    # Emulation of the official scheme: raw-component steps, one fixed level, f = g + h, 399 expansions,
    # L1 cost, no early stop.
    "paper": RefineConfig(metric="sad", neighbourhood="paper", polish=False, max_expansions_per_level=399,
                          max_expansions=399, patience=0, heuristic_weight=1.0, depth_cost=1.0, coarse_scale=1.0,
                          max_shift=0.5, max_rotation_deg=5.0, acceptance="cost"),
}
