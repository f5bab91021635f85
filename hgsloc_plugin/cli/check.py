"""Do the map and the poses agree? Render a sample of poses, compare with the photos, name a convention error.

The classic failure of render-and-compare refinement is a map and poses in different frames or conventions:
camera-to-world given for world-to-camera, OpenGL camera axes instead of OpenCV, quaternions in ``x y z w``
order, a global scale. :func:`check_poses` scores the sample as given and under each of these readings with the
default heuristic (``cs``, local structure, at ``SIDE`` px) and says which, if any, fits clearly better.

A localizer's pose is a few centimetres and a degree or two off, and on a real map that alone raises the cost of
the pose as given towards that of an unrelated image (snow, median cs cost of the sample: 0.26 at the SfM poses,
0.36 at 3 cm-equivalent / 1 deg, 0.46 at 10 cm / 3 deg, 0.53 at 20 cm / 5 deg; wrong readings 0.46-1.0; lego
0.20, 0.90 from 3 cm / 1 deg on). So when the raw costs are not conclusive the pose as given is first
**aligned** (then, until one settles it, the other readings in order of raw cost): the refiner's gradient route
(``RefineConfig.preset("gradient")``, coarse to fine up to ``ALIGN_SIDE`` px) moves each to its nearest cost
minimum, scored again at ``SIDE`` px, and the rule is applied to the aligned costs. A prior that is merely off
lands on the map's own minimum (snow: 0.27 from every prior up to 20 cm / 5 deg; lego 0.16-0.23 from 3-10 cm),
while a wrong frame or convention stays unrelated (snow 0.47-0.71, lego 0.78-1.0). Lego priors 20 cm / 5 deg
off are beyond the route's reach: "disagree", as before.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import Camera
from ..core.costs import cost_from_window
from ..core.image import load_image, undistort
from ..core.pose import Pose
from ..core.scene import GaussianScene
from ..refine import RefineConfig, Refiner
from ..refine.plan import median_depth
from ..refine.scorer import Scorer
from ..render import get_renderer

logger = logging.getLogger("hgsloc_plugin")

SIDE = 200
ALIGN_SIDE = 100  # the alignment's finest size (pixels, longer side)
# thresholds on the masked cs cost (where they come from: benchmarks/defaults.md)
GOOD = 0.55  # the best reading must cost less than this
CLEARLY_BETTER = 0.7  # ... and less than this fraction of the second-best reading
MASK_ALPHA = 0.5  # compare where the map renders something: an empty rendering costs 1, not a match
#: ... but a reading that renders only a sliver of the image is no match either: its similarity is spread over at
#: least this share of the pixels the query's best-covered reading renders (snow, 2 % / 1 deg priors: a quaternion
#: read x y z w rendered 16 of 29,304 pixels, similar there, and passed for the right reading at cs 0.03)
MIN_COVER = 0.5
_FLIP = np.diag([1.0, -1.0, -1.0])

#: reading name -> (pose transform, how to fix the input)
HYPOTHESES: dict[str, tuple[Callable[[Pose], Pose], str]] = {
    "as given": (lambda p: p, ""),
    "inverted": (lambda p: p.inv(), "the file holds camera-to-world poses: invert them (world-to-camera expected)"),
    "OpenGL axes": (lambda p: Pose.from_Rt(_FLIP @ p.R, _FLIP @ p.tvec),
                    "camera axes are OpenGL/Blender (y up, z back): flip y and z, R' = diag(1,-1,-1) R, "
                    "t' = diag(1,-1,-1) t"),
    "xyzw quaternion": (lambda p: Pose(np.r_[p.qvec[3], p.qvec[:3]], p.tvec),
                        "quaternions are in x y z w order: reorder them to w x y z"),
    "scale x2": (lambda p: Pose(p.qvec, 0.5 * p.tvec),
                 "translations are twice the map's scale: multiply every t by 0.5"),
    "scale x0.5": (lambda p: Pose(p.qvec, 2.0 * p.tvec),
                   "translations are half the map's scale: multiply every t by 2"),
}


@dataclass
class CheckReport:
    """Per-query costs under each reading, the verdict and a hint.

    Attributes:
        costs: reading -> [n] cs cost (0 identical structure, ~1 unrelated) of each sampled query.
        aligned: reading -> [n] cs cost after the alignment (readings aligned only; empty when the raw costs
            were conclusive); the verdict uses the lower of the two per query.
        psnr / ssim: [n] of the poses as given (for humans).
        verdict: "ok", "convention error" or "disagree".
        reading: the best-fitting reading; hint: how to fix the input (empty when ok).
        unreadable: sampled queries whose image could not be read -> why (the check then fails).
    """

    names: list[str]
    costs: dict[str, list[float]]
    psnr: list[float]
    ssim: list[float]
    verdict: str
    reading: str
    hint: str
    figures: list[str] = field(default_factory=list)
    aligned: dict[str, list[float]] = field(default_factory=dict)
    unreadable: dict[str, str] = field(default_factory=dict)
    depths: list[float] = field(default_factory=list)

    @property
    def median_depth(self) -> float:
        """The map's median depth at the sampled poses as given (scene units; nan when none was read)."""
        return float(np.median(self.depths)) if self.depths else float("nan")

    @property
    def scale_for_2m(self) -> float:
        """``hgsloc evaluate --scale`` (metres per scene unit) that takes the median depth as 2 m, 7-Scenes' typical
        depth: errors in "cm-eq", comparable across maps of any scale."""
        return 2.0 / self.median_depth

    def median(self, reading: str = "as given") -> float:
        """Median cost of a reading: after the alignment when it was aligned, else as read."""
        return float(np.median(_effective(self.costs, self.aligned)[reading]))

    @property
    def agrees(self) -> bool:
        """The poses and the map agree (over the queries that could be read)."""
        return self.verdict == "ok"

    @property
    def ok(self) -> bool:
        """They agree and every sampled query could be read."""
        return self.agrees and not self.unreadable

    def message(self) -> str:
        text = self._agreement()
        if self.unreadable:
            name, why = next(iter(self.unreadable.items()))
            text += (f"; {len(self.unreadable)} sampled quer{'y' if len(self.unreadable) == 1 else 'ies'} could not "
                     f"be read (first: {name}: {why})")
        return text

    def _agreement(self) -> str:
        given = self.median()
        if self.agrees:
            how = ""
            if "as given" in self.aligned:
                raw = float(np.median(self.costs["as given"]))
                how = (f" after aligning each pose to its nearest minimum (as given {raw:.3f}: the poses are some "
                       "pixels off, which the refinement is for)")
            return (f"poses and map agree: median cs cost {given:.3f} over {len(self.names)} queries{how} (< {GOOD}, "
                    "clearly below every other reading)")
        if self.verdict == "convention error":
            return (f"poses and map disagree as given (median cs cost {given:.3f}); read as '{self.reading}' they "
                    f"agree ({self.median(self.reading):.3f}): {self.hint}")
        return (f"poses and map disagree (median cs cost {given:.3f}) and no usual convention error clearly "
                f"explains it (best: '{self.reading}' {self.median(self.reading):.3f}): are the poses in the map's "
                "frame (same SfM reconstruction and scale), the intrinsics right and the background colour right? (or "
                "further off than the check's alignment reaches, e.g. 20 cm / 5 deg on a small object)")

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "reading": self.reading, "hint": self.hint, "message": self.message(),
                "queries": {n: {"psnr": self.psnr[k], "ssim": self.ssim[k],
                                **{h: c[k] for h, c in self.costs.items()}} for k, n in enumerate(self.names)},
                "median": {h: self.median(h) for h in self.costs},
                "aligned": {h: dict(zip(self.names, c)) for h, c in self.aligned.items()}, "figures": self.figures,
                "unreadable": self.unreadable, "median_depth": self.median_depth, "scale_for_2m": self.scale_for_2m}


def _effective(costs: dict[str, list[float]], aligned: dict[str, list[float]]) -> dict[str, list[float]]:
    """Per reading and query, the aligned cost where there is one and it is lower, else the raw cost."""
    return {h: [min(a, b) for a, b in zip(c, aligned[h])] if h in aligned else list(c) for h, c in costs.items()}


def _verdict(costs: dict[str, list[float]]) -> tuple[str, str, bool]:
    """(best reading, second best, whether the best is good and clearly better than the second)."""
    med = {h: float(np.median(c)) for h, c in costs.items()}
    best, second = sorted(med, key=med.get)[:2]
    return best, second, med[best] < GOOD and med[best] <= CLEARLY_BETTER * med[second]


def _sample(names: list[str], n: int) -> list[str]:
    if len(names) <= n:
        return names
    idx = np.linspace(0, len(names) - 1, n).round().astype(int)
    return [names[i] for i in dict.fromkeys(idx.tolist())]


def check_poses(scene: GaussianScene, poses: Mapping[str, Pose | None], image_of: Callable[[str], Path],
                intrinsics: Callable[[str, int, int], Camera], *, sample: int = 8, background=(0.0, 0.0, 0.0),
                figures: Path | None = None, align: bool = True) -> CheckReport:
    """Score a sample of ``poses`` against their photos as given and under each reading of ``HYPOTHESES``.

    Args:
        poses: name -> world-to-camera pose (None entries are skipped). image_of: name -> image path.
        intrinsics: (name, width, height) -> Camera. sample: queries to use (evenly spaced, deterministic).
        figures: write query | rendering side by side per sampled query here.
        align: when the raw costs are not conclusive, align the pose as given (then the other readings in order
            of raw cost, until one settles it) to its nearest cost minimum first (see the module docstring);
            False: raw costs only.
    """
    import kornia
    import torch

    names = _sample([n for n, p in poses.items() if p is not None], sample)
    if not names:
        raise ValueError("no usable pose to check")
    renderer = get_renderer(scene)
    costs: dict[str, list[float]] = {h: [] for h in HYPOTHESES}
    psnr, ssim, figs = [], [], []
    used, data, unreadable, depths, covers = [], [], {}, [], []
    for name in names:
        try:
            img = load_image(image_of(name), name=name, background=background)
        except (FileNotFoundError, OSError, ValueError, KeyError) as exc:  # refine records it per query
            logger.debug("check: cannot read %s: %s", name, exc)  # the report's message names it, once
            unreadable[name] = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
            continue
        used.append(name)
        img, full = undistort(img, intrinsics(name, img.shape[1], img.shape[0]))
        data.append((img, full))
        depths.append(median_depth(scene, full, poses[name]))
        cam = full.with_max_side(SIDE)
        scorer = Scorer(renderer, "cs", background, MASK_ALPHA)
        scorer.set_query(cam, img)
        sums = renderer.window_cost(cam, [f(poses[name]) for f, _ in HYPOTHESES.values()],
                                    scorer.window_query(cam, img), background, MASK_ALPHA)
        covers.append(MIN_COVER * float(np.max(sums[:, 1])))
        for h, c in zip(HYPOTHESES, covered_cost(sums, covers[-1])):
            costs[h].append(float(c))
        rgb, _, _ = renderer.render_full(cam, [poses[name]], background)
        q = scorer.query
        psnr.append(float(10 * np.log10(1.0 / max(float(np.mean((rgb[0] - q) ** 2)), 1e-12))))
        a, b = (torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None] for x in (rgb[0], q))
        ssim.append(float(kornia.metrics.ssim(a, b, 11).mean()))
        if figures is not None:
            from ..evaluation.viz import check_figure

            path = Path(figures) / (Path(name.replace("/", "_")).stem + ".check.png")
            check_figure(q, rgb[0], name, costs["as given"][-1], path)
            figs.append(str(path))
    if not used:
        name, why = next(iter(unreadable.items()))
        raise ValueError(f"no query image of the sample could be read (first: {name}: {why})")
    names = used
    best, second, clear = _verdict(costs)
    aligned: dict[str, list[float]] = {}
    if not clear and align:
        others = sorted((h for h in costs if h != "as given"), key=lambda h: float(np.median(costs[h])))
        for h in ["as given"] + others:  # in order of raw cost, until one settles it
            aligned[h] = _aligned_costs(scene, poses, names, data, covers, HYPOTHESES[h][0], background)
            best, second, clear = _verdict(_effective(costs, aligned))
            if clear:
                break
    if clear and best == "as given":
        verdict, reading, hint = "ok", best, ""
    elif clear:
        verdict, reading, hint = "convention error", best, HYPOTHESES[best][1]
    else:
        verdict, reading, hint = "disagree", best, ""
    return CheckReport(names, costs, psnr, ssim, verdict, reading, hint, figs, aligned, unreadable, depths)


def covered_cost(sums: np.ndarray, cover: float) -> np.ndarray:
    """The check's cost of poses [B] from their windowed cs sums [B, 2] (similarity sum, pixels compared): one less
    the mean similarity over at least ``cover`` pixels (the pixels a pose does not render count as unrelated)."""
    sums = np.asarray(sums, np.float64)
    return cost_from_window(np.column_stack([sums[:, 0], np.maximum(sums[:, 1], cover)]))


def _aligned_costs(scene: GaussianScene, poses: Mapping[str, Pose], names: list[str], data: list,
                   covers: list[float], reading, background) -> list[float]:
    """The check's cost of each sampled query after the refiner's gradient route moved the reading's pose to its
    nearest minimum (at ``ALIGN_SIDE`` px and below; the raw pose's cost where the route fails)."""
    refiner = Refiner(scene, RefineConfig.preset("gradient", background=tuple(background),
                                                 score_max_side=ALIGN_SIDE, polish_max_side=ALIGN_SIDE))
    scorer = Scorer(refiner.renderer, "cs", background, MASK_ALPHA)
    out = []
    for name, (img, cam), cover in zip(names, data, covers):
        start = reading(poses[name])
        res = refiner.try_refine(img, cam, start, name=name)
        moved = res.search_pose if res.error is None and res.search_pose is not None else start
        side = cam.with_max_side(SIDE)
        sums = refiner.renderer.window_cost(side, [moved], scorer.window_query(side, img), background, MASK_ALPHA)
        out.append(float(covered_cost(sums, cover)[0]))
        logger.debug("check: %s aligned (%s) to cs cost %.3f", name, res.rejected or "accepted", out[-1])
    return out
