"""The map's floor: how far the map's own cost minimum lies from views whose poses are known.

A map fitted to photos renders each view a little off (geometry, exposure, the photos' own pose errors), so the
refined pose of a perfect prior is not the prior: it is the map's nearest minimum. Over views with known poses
(training views, or any the user trusts) the offsets of those minima are the map's floor, which no statistic of
one query image shows (``benchmarks/map_floor.md``). As 3-D standard deviations it goes into every polished
pose's covariance (``Tuning.map_floor_depth`` / ``map_floor_deg``): the sigmas then cover the map's error, and a
prior of known error is fused with the refined pose by the map's real precision.

The same views give the cost level right answers reach on the map: the cs cost at each view's minimum (at the
judging size). A refined pose whose cost lies above the one-sided 99.9 % prediction bound of those costs (log-normal,
Student's t with n - 1 degrees of freedom: :func:`cost_bound`) is refused (``Tuning.map_cost_bound``): a right answer
on a view like the known ones lies above it one time in a thousand, a wrong minimum far from the truth far more often.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from ..core.pose import rotation_angle_deg


@dataclass(frozen=True)
class MapFloor:
    """The map's floor over ``n`` views.

    Attributes:
        depth: root mean square of the camera-centre offsets, as a fraction of each view's median depth (the
            3-D standard deviation ``Tuning.map_floor_depth`` takes).
        deg: root mean square of the rotation offsets in degrees (``Tuning.map_floor_deg``).
        offsets: [n, 2] per view: (centre offset / median depth, rotation offset in degrees), in input order.
        names: the views' names, in input order.
        costs: [n] per view: the cs cost at its minimum (at the judging size), in input order; empty when not
            measured.
    """

    depth: float
    deg: float
    offsets: np.ndarray
    names: tuple[str, ...]
    costs: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n(self) -> int:
        return len(self.names)

    @functools.cached_property
    def cost_bound(self) -> float | None:
        """The cs cost above which a refined pose is refused (:func:`cost_bound`, computed once); None below 3
        measured costs."""
        return cost_bound(self.costs)

    def flag(self) -> str:
        """The ``hgsloc refine --map-floor`` value that declares this floor (and its cost bound, when known)."""
        bound = self.cost_bound
        return f"{100.0 * self.depth:.3g}%,{self.deg:.3g}deg" + ("" if bound is None else f",{bound:.3g}cs")

    def tuning(self) -> dict:
        """The ``Tuning`` fields that declare this floor (``map_cost_bound`` only when known)."""
        out = {"map_floor_depth": self.depth, "map_floor_deg": self.deg}
        if self.cost_bound is not None:
            out["map_cost_bound"] = self.cost_bound
        return out

    def without(self, name: str) -> MapFloor:
        """This floor measured without view ``name`` (for a query that is one of the views measured)."""
        keep = [i for i, n in enumerate(self.names) if n != name]
        costs = self.costs[keep] if len(self.costs) == len(self.names) else None
        return floor_from_offsets(self.offsets[keep], [self.names[i] for i in keep], costs)


def floor_from_offsets(offsets: np.ndarray, names: Iterable[str], costs: np.ndarray | None = None) -> MapFloor:
    """:class:`MapFloor` of ``offsets`` [n, 2] (centre offset / median depth, degrees) and, when given, the cs cost
    at each view's minimum ``costs`` [n]; ValueError when n = 0 or the costs do not match the views."""
    offsets = np.asarray(offsets, np.float64).reshape(-1, 2)
    if len(offsets) == 0:
        raise ValueError("the map's floor needs at least one view with a known pose")
    costs = np.zeros(0) if costs is None else np.asarray(costs, np.float64).reshape(-1)
    if len(costs) not in (0, len(offsets)):
        raise ValueError(f"the map's floor: {len(costs)} costs for {len(offsets)} views")
    rms = np.sqrt(np.mean(offsets ** 2, axis=0))
    return MapFloor(float(rms[0]), float(rms[1]), offsets, tuple(names), costs)


#: the share of right answers, on views like the known ones, that :func:`cost_bound` keeps
COST_BOUND_LEVEL = 0.999


def _betainc(a: float, b: float, x: float) -> float:
    """The regularised incomplete beta function ``I_x(a, b)``, 0 <= x <= 1: its continued fraction (modified Lentz),
    on the side of ``x`` where it converges fast (``I_x(a, b) = 1 - I_{1-x}(b, a)``)."""
    if x <= 0.0 or x >= 1.0:
        return 0.0 if x <= 0.0 else 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _betainc(b, a, 1.0 - x)
    tiny = 1e-300
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)) / a
    f, c, d = 1.0, 1.0, 0.0
    for i in range(600):
        m = i // 2
        if i == 0:
            num = 1.0
        elif i % 2 == 0:
            num = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))
        else:
            num = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        d = 1.0 + num * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + num / c
        c = c if abs(c) > tiny else tiny
        f *= c * d
        if abs(c * d - 1.0) < 1e-15:
            break
    return front * (f - 1.0)


def t_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile (0.5 < p < 1) of Student's t distribution with ``dof`` >= 1 degrees of freedom, by bisection
    on its upper tail ``P(T > t) = I_x(dof / 2, 1 / 2) / 2``, ``x = dof / (dof + t^2)``."""
    if not (0.5 < p < 1.0 and dof >= 1):
        raise ValueError(f"t_quantile needs 0.5 < p < 1 and dof >= 1, got {p}, {dof}")

    def upper_tail(t: float) -> float:
        return 0.5 * _betainc(dof / 2.0, 0.5, dof / (dof + t * t))

    lo, hi = 0.0, 1.0
    while upper_tail(hi) > 1.0 - p:
        lo, hi = hi, 2.0 * hi
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if upper_tail(mid) > 1.0 - p else (lo, mid)
    return 0.5 * (lo + hi)


def cost_bound(costs: np.ndarray, level: float = COST_BOUND_LEVEL) -> float | None:
    """The one-sided ``level`` prediction bound of a new view's cs cost at its minimum, from the costs [n] at known
    views' minima: ``exp(m + t s sqrt(1 + 1 / n))``, ``m`` / ``s`` the mean / standard deviation of their logs and
    ``t`` Student's ``level`` quantile with n - 1 degrees of freedom. None with fewer than 3 positive finite costs."""
    c = np.asarray(costs, np.float64).reshape(-1)
    c = c[np.isfinite(c) & (c > 0)]
    if len(c) < 3:
        return None
    logs = np.log(c)
    spread = float(np.std(logs, ddof=1)) * math.sqrt(1.0 + 1.0 / len(c))
    return float(math.exp(float(np.mean(logs)) + t_quantile(level, len(c) - 1) * spread))


def map_floor(refiner, views: Iterable[tuple]) -> MapFloor:
    """Measure the map's floor on views with known poses.

    Args:
        refiner: an ``HGSLocPlugin`` / ``Refiner`` on the map (its configuration's routes and sizes are the ones
            measured; the offset is taken before any fusion with a declared prior error).
        views: (image, camera, known world-to-camera ``Pose``, name) per view.

    Returns:
        :class:`MapFloor`: each view refined from its own known pose; its offset is the distance from the known
        pose to the pose the acceptance rule judged (``RefineResult.search_pose``: the map's nearest minimum).
    """
    from ..refine.plan import median_depth

    offsets, names, costs = [], [], []
    for image, camera, pose, name in views:
        r = refiner.refine(image, camera, pose, name=name)
        if r.search_pose is None:
            raise ValueError(f"{name}: no refined pose to measure the map's floor with ({r.rejected})")
        depth = median_depth(refiner.scene, camera, pose)
        found = r.search_pose
        offsets.append((float(np.linalg.norm(found.centre() - pose.centre())) / depth,
                        rotation_angle_deg(found.R, pose.R)))
        names.append(name)
        costs.append(r.search_cost)
    if not all(math.isfinite(v) for o in offsets for v in o):
        raise ValueError("the map's floor: a non-finite offset (a view the map does not render?)")
    return floor_from_offsets(np.array(offsets), names, np.array(costs))
