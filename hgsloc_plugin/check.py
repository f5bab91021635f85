"""Do the map and the poses agree? Render a sample of poses, compare with the photos, name a convention error.

The classic failure of render-and-compare refinement is a map and poses in different frames or conventions:
camera-to-world given for world-to-camera, OpenGL camera axes instead of OpenCV, quaternions in ``x y z w``
order, a global scale. :func:`check_poses` scores the sample as given and under each of these readings with the
default heuristic (``cs``, local structure, at ``SIDE`` px) and says which, if any, fits clearly better.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera
from .image import load_image
from .pose import Pose
from .refine.scorer import Scorer
from .render import get_renderer
from .scene import GaussianScene

logger = logging.getLogger("hgsloc_plugin")

SIDE = 200
# Measured (median masked cs cost of the true poses; the wrong readings): snow 0.263 (0.46-1.0), lego 0.496
# (0.81-1.0); true poses moved by a random rigid transform: snow best reading 0.461, second 0.619.
GOOD = 0.55  # the best reading must cost less than this
CLEARLY_BETTER = 0.7  # ... and less than this fraction of the second-best reading
MASK_ALPHA = 0.5  # compare where the map renders something: an empty rendering costs 1, not a match
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
        psnr / ssim: [n] of the poses as given (for humans).
        verdict: "ok", "convention error" or "disagree".
        reading: the best-fitting reading; hint: how to fix the input (empty when ok).
    """

    names: list[str]
    costs: dict[str, list[float]]
    psnr: list[float]
    ssim: list[float]
    verdict: str
    reading: str
    hint: str
    figures: list[str] = field(default_factory=list)

    def median(self, reading: str = "as given") -> float:
        return float(np.median(self.costs[reading]))

    @property
    def ok(self) -> bool:
        return self.verdict == "ok"

    def message(self) -> str:
        given = self.median()
        if self.ok:
            return (f"poses and map agree: median cs cost {given:.3f} over {len(self.names)} queries (< {GOOD}, "
                    "clearly below every other reading)")
        if self.verdict == "convention error":
            return (f"poses and map disagree as given (median cs cost {given:.3f}); read as '{self.reading}' they "
                    f"agree ({self.median(self.reading):.3f}): {self.hint}")
        return (f"poses and map disagree (median cs cost {given:.3f}) and no usual convention error clearly "
                f"explains it (best: '{self.reading}' {self.median(self.reading):.3f}): are the poses in the map's "
                "frame (same SfM reconstruction and scale), the intrinsics right and the background colour right?")

    def to_dict(self) -> dict:
        return {"verdict": self.verdict, "reading": self.reading, "hint": self.hint, "message": self.message(),
                "queries": {n: {"psnr": self.psnr[k], "ssim": self.ssim[k],
                                **{h: c[k] for h, c in self.costs.items()}} for k, n in enumerate(self.names)},
                "median": {h: self.median(h) for h in self.costs}, "figures": self.figures}


def _sample(names: list[str], n: int) -> list[str]:
    if len(names) <= n:
        return names
    idx = np.linspace(0, len(names) - 1, n).round().astype(int)
    return [names[i] for i in dict.fromkeys(idx.tolist())]


def check_poses(scene: GaussianScene, poses: Mapping[str, Pose | None], image_of: Callable[[str], Path],
                intrinsics: Callable[[str, int, int], Camera], *, sample: int = 8, background=(0.0, 0.0, 0.0),
                figures: Path | None = None) -> CheckReport:
    """Score a sample of ``poses`` against their photos as given and under each reading of ``HYPOTHESES``.

    Args:
        poses: name -> world-to-camera pose (None entries are skipped). image_of: name -> image path.
        intrinsics: (name, width, height) -> Camera. sample: queries to use (evenly spaced, deterministic).
        figures: write query | rendering side by side per sampled query here.
    """
    import kornia
    import torch

    names = _sample([n for n, p in poses.items() if p is not None], sample)
    if not names:
        raise ValueError("no usable pose to check")
    renderer = get_renderer(scene)
    costs: dict[str, list[float]] = {h: [] for h in HYPOTHESES}
    psnr, ssim, figs = [], [], []
    used = []
    for name in names:
        try:
            img = load_image(image_of(name), name=name, background=background)
        except (FileNotFoundError, OSError, ValueError, KeyError) as exc:  # refine records it per query
            logger.warning("check: skipping %s: %s", name, exc)
            continue
        used.append(name)
        cam = intrinsics(name, img.shape[1], img.shape[0]).with_max_side(SIDE)
        scorer = Scorer(renderer, "cs", background, MASK_ALPHA)
        scorer.set_query(cam, img)
        for h, (f, _) in HYPOTHESES.items():
            costs[h].append(float(scorer([f(poses[name])])[0]))
        rgb, _, _ = renderer.render_full(cam, [poses[name]], background)
        q = scorer.query
        psnr.append(float(10 * np.log10(1.0 / max(float(np.mean((rgb[0] - q) ** 2)), 1e-12))))
        a, b = (torch.from_numpy(np.ascontiguousarray(x)).permute(2, 0, 1)[None] for x in (rgb[0], q))
        ssim.append(float(kornia.metrics.ssim(a, b, 11).mean()))
        if figures is not None:
            from .viz import save_png

            path = Path(figures) / (name.replace("/", "_") + ".check.png")
            save_png(np.concatenate([q, rgb[0]], axis=1), path)
            figs.append(str(path))
    if not used:
        raise ValueError("no query image of the sample could be read")
    names = used
    med = {h: float(np.median(c)) for h, c in costs.items()}
    order = sorted(med, key=med.get)
    best, second = order[0], order[1]
    clear = med[best] < GOOD and med[best] <= CLEARLY_BETTER * med[second]
    if clear and best == "as given":
        verdict, reading, hint = "ok", best, ""
    elif clear:
        verdict, reading, hint = "convention error", best, HYPOTHESES[best][1]
    else:
        verdict, reading, hint = "disagree", best, ""
    return CheckReport(names, costs, psnr, ssim, verdict, reading, hint, figs)
