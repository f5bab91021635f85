"""RefineConfig: every setting of the pose search, with named presets stored as data."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..costs import METRICS as _COSTS
from ..costs import SEARCH_METRICS as METRICS


@dataclass(frozen=True, kw_only=True)
class RefineConfig:
    """Settings of :class:`~hgsloc_plugin.HGSLocPlugin`.

    Attributes:
        metric: heuristic h: "cs" (default; 1 - mean of SSIM's contrast-structure term over 11x11 Gaussian
            windows: compares local structure, so it holds on real photographs against imperfect maps and under
            exposure changes), "ssim" (1 - SSIM), "sad" (paper's L1 sum), "psnr" (100 - PSNR), "ncc"
            (1 - zero-mean NCC) or "affine" (L1-scaled RMS residual after a per-channel gain/offset fit).
            All run in the kernels (``kernels/blend.py``, ``kernels/window.py``).
        neighbourhood: "lattice" (12 moves: +-dr about each camera axis, +-dt along each; proper rotations)
            or "paper" (14 moves: +-d on each raw q, t component; quaternion normalised before rendering).
        levels: explicit (rotation step in degrees, translation step in scene units) per level, coarse to fine;
            empty = chosen from the scene depth and the camera (see ``level_pixels``).
        level_pixels: image motion in scoring pixels of each automatic level's step. None: (4, 2, 1) when the
            polish runs (it finishes below one pixel: measured in benchmarks/refine.py as accurate as the levels
            down to 0.125 px + polish on the real snow photos and the room, with about half the renders), else
            (4, 2, 1, 0.5, 0.25, 0.125).
        max_expansions_per_level / max_expansions: expansion budgets (per level / whole query).
        patience: consecutive expansions without a new best before a level stops (0 = never stop early).
        pivot: lattice rotations turn about a point on the optical axis at the median scene depth (decouples
            rotation from translation); False turns about the camera centre.
        pattern_moves: also score the node that repeats the move which reached the expanded node.
        heuristic_weight / depth_cost: f = depth_cost * g + heuristic_weight * h (paper: 1 and 1;
            depth_cost 0 gives pure greedy best-first).
        score_max_side: longer image side at which the fine levels score; the first ``coarse_levels``
            levels (image pyramid) use ``coarse_scale`` times that, but never fewer than ``coarse_min_side``
            pixels. Measured: reducing more than the first two levels costs accuracy and time.
        max_shift / max_rotation_deg: trust region around the coarse pose: camera-centre shift in scene units
            and rotation in degrees. None = ``trust_steps`` times the coarsest level's step (the expected error
            of a coarse pose is a few coarse steps; with the default levels 8 x 4 px of image motion, e.g. about
            23 % of the median depth and 13 deg at 160 px and a 60 deg field of view).
        trust_steps: multiple of the coarsest step used for an automatic trust region.
        prior_error / prior_error_deg: the coarse poses' typical (median) error, camera centre in scene units
            and rotation in degrees, when known (a localizer's published accuracy, its inlier count:
            ``adapters/confidence.py``); None (default): unknown. An accepted refined pose is then fused with
            the prior (``refine/trust.py``, ``fuse_with_prior``: the posterior mean of the refined pose with its
            covariance and the prior with a per-axis spread of 1.3x its median error); where the fusion's cost
            is not below the prior's, the prior is kept (``rejected: "prior more precise"``). A real map's
            minimum can lie centimetres from the true pose along a direction the image barely constrains (snow
            query 0: 2.9 cm-equivalent) in a sharp, significant valley; no image cost tells that drift from a
            correction, the prior's own accuracy can (``benchmarks/trust.py``: with a declared 1 cm / 0.5 deg,
            Marepo's median, or ACE's inlier counts no snow, lego or room query ends worse). Only one given: the
            prior pulls only in that part.
        acceptance: "trust" (default): the search's pose is returned only when it passes the acceptance rule
            of ``refine/trust.py`` (significant, sharp, inside the region, consistent across levels), else the
            coarse pose with the reason; "cost": whenever its cost is lower (the paper's rule).
        working_set: render each query's search from the Gaussians that some pose near the poses it scores
            can see (``working_set.WorkingSet``: selected for a region of ``working_set_pixels`` around the
            first poses scored, selected again when the search leaves it; conservative, so the images are
            bit-identical to the whole map's) instead of the whole map per render; only for maps of at least
            ``working_set_min`` Gaussians (``benchmarks/map_scale.py``, per query vs the whole map over three
            runs: 0.97-1.05x at 49k, 0.87-1.20x at 195k, 1.05-1.06x at 488k, 1.04-1.37x at 975k, within this
            machine's run-to-run noise below 1M; peak memory 0.42-0.79x; small maps gain little because the
            projection rejects invisible Gaussians early).
        working_set_pixels: the selection region's radius in image motion at the final scoring size (pixels:
            rotation and camera shift at the median depth); a smaller region keeps fewer Gaussians and is left
            more often.
        coarse_lod_pixels: the coarse (pyramid) levels render a level of detail in which Gaussians of at most
            this many pixels are merged per cell of this size (``lod.py``; approximate, built once per query;
            only with a working set); None (default): the exact map at every level. Measured at 2 px
            (``benchmarks/map_scale.py``, two runs): 0.90-1.37x per query from 195k to 1M Gaussians, and the
            1M outcomes changed with it (better in one run, worse in the other), hence opt-in.
        polish: after the search, a Levenberg-Marquardt polish on the cs cost from the kernels' analytic pose
            derivatives (``refine/polish.py``) at ``polish_max_side``; keeps the search's pose unless the cost
            falls. Only for the cs metric (the derivatives are those of cs); other metrics skip it.
        gradient_first: try the gradient-only route first (Levenberg-Marquardt from the coarse pose, as with
            ``search=False``) and run the lattice search + polish only when its pose fails the acceptance rule
            (``RefineResult.route``, ``gradient_rejected``); a coarse pose refused only as insignificant in a
            sharp, well-aligned minimum (``trust.settled``) is kept without a search. Measured
            (``benchmarks/refine.py``, ``benchmarks/trust.py``): the same outcomes as search + polish on every
            row of the real snow photos, lego, the room and the donut, with 2.0-3.0x fewer render-equivalents on
            snow and 1.4-3.1x on the room over two runs (priors from the truth to 10 cm / 3 deg), 2.4-3.9x on
            lego up to 3 cm (0.8x at 10 cm: a query the gradient cannot reach pays both routes, as do 30 cm /
            10 deg priors), and 1.28-1.64x less time per query on the 1M-Gaussian room (``benchmarks/map_scale.py``,
            two runs).
            False: always search (the "search" preset).
        polish_iterations: derivative passes at most per polish (one pass costs 2-10 renders of the search,
            growing with the polish size). Far from the minimum the steps are short: on the donut a polish from
            3.5 cm-eq took 13 passes to 0.05 cm-eq (8 stopped half way).
        polish_max_side: longer image side of the polish (the query's own size when smaller). Measured on the
            room's 320x240 queries: polishing at 320 px reaches 0.04 cm, at 200 px (a downsampled query) 0.26 cm,
            no better than the search: precision needs the query's own pixels.
        search: run the lattice search. False with ``polish`` = gradient only: Levenberg-Marquardt from the
            coarse pose, coarse to fine over the scoring sizes (the "gradient" preset).
        mask_alpha: ignore pixels whose rendered alpha is below this (0 = use all pixels).
        background: RGB behind the Gaussians (the colour the map was trained with).
        resize_query: resize a query whose size differs from the camera's instead of raising.
        paper_step_q / paper_step_t: raw-component steps of the "paper" neighbourhood.
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


PRESETS: dict[str, RefineConfig] = {
    "default": RefineConfig(),
    # Levenberg-Marquardt from the coarse pose, no lattice search (where each part is needed: benchmarks/).
    "gradient": RefineConfig(search=False),
    # Always the lattice search + polish (no gradient-first route).
    "search": RefineConfig(gradient_first=False),
    "fast": RefineConfig(max_expansions_per_level=15, max_expansions=60, score_max_side=120, polish_iterations=4,
                         polish_max_side=240),
    "accurate": RefineConfig(level_pixels=(6.0, 3.0, 1.5, 0.75), max_expansions_per_level=40, max_expansions=280,
                             patience=3, score_max_side=240, coarse_scale=1.0, polish_iterations=12,
                             polish_max_side=640),
    # Emulation of the official scheme: raw-component steps, one fixed level, f = g + h, 399 expansions,
    # L1 cost, no early stop.
    "paper": RefineConfig(metric="sad", neighbourhood="paper", polish=False, max_expansions_per_level=399,
                          max_expansions=399, patience=0, heuristic_weight=1.0, depth_cost=1.0, coarse_scale=1.0,
                          max_shift=0.5, max_rotation_deg=5.0, acceptance="cost"),
}
