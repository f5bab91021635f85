"""Best-first (A*-style) search over an integer lattice of poses around a base pose.

Two neighbourhoods:
- :class:`LatticeSpace` (default): key (i, j, k, l, m, n) is the pose exp([i, j, k] dr) applied about the camera
  centre, then a translation [l, m, n] dt along the camera axes, composed with the base pose. Every node is a
  proper rotation and keys are integers, so the closed list never compares floats.
- :class:`PaperSpace`: the published neighbourhood, +-d on each raw (qw, qx, qy, qz, tx, ty, tz); the
  quaternion is normalised before rendering (the official code never normalises it).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..core.pose import Pose, rotmat_to_qvec, so3_exp


@dataclass
class LevelStats:
    """One search level: its steps (degrees, scene units), scoring size, expansions, renders, best cost and why
    it stopped."""

    step_rot_deg: float
    step_t: float
    width: int
    height: int
    expansions: int
    renders: int
    best_cost: float
    stopped: str


class LatticeSpace:
    """Camera-frame rotation/translation lattice around ``base`` (steps in radians and scene units).

    Rotations turn the camera about a pivot on its optical axis at ``pivot_depth`` (0: about the camera
    centre). With the pivot at the scene's median depth, a rotation step keeps the image centre in place and a
    translation step shifts the image: the two are nearly decoupled, so axis moves can follow the narrow
    rotation/translation valley of the cost instead of zig-zagging across it.
    """

    dim = 6

    def __init__(self, base: Pose, step_rot_rad: float, step_t: float, pivot_depth: float = 0.0):
        self.base, self.dr, self.dt = base, float(step_rot_rad), float(step_t)
        self.pivot = np.array([0.0, 0.0, float(pivot_depth)])
        self._R, self._t = base.R, base.tvec
        # a zero step makes those axes inert: no moves along them
        self.axes = [a for a in range(6) if (self.dr if a < 3 else self.dt) > 0]

    def pose(self, key: tuple[int, ...]) -> Pose:
        k = np.asarray(key, dtype=np.float64)
        dR = so3_exp(k[:3] * self.dr)
        R = dR @ self._R
        t = dR @ (self._t - self.pivot) + self.pivot + k[3:] * self.dt
        return Pose(rotmat_to_qvec(R), t)

    def neighbours(self, key: tuple[int, ...]) -> list[tuple[int, ...]]:
        out = []
        for a in self.axes:
            for s in (1, -1):
                k = list(key)
                k[a] += s
                out.append(tuple(k))
        return out


class PaperSpace:
    """The official neighbourhood: +-step on each raw component of (q, t), 14 children."""

    dim = 7

    def __init__(self, base: Pose, step_q: float, step_t: float):
        self.base, self.dq, self.dt = base, float(step_q), float(step_t)
        self.raw = np.concatenate([base.qvec, base.tvec])

    def pose(self, key: tuple[int, ...]) -> Pose:
        k = np.asarray(key, dtype=np.float64)
        v = self.raw + np.concatenate([k[:4] * self.dq, k[4:] * self.dt])
        return Pose(v[:4], v[4:])  # normalised here

    def neighbours(self, key: tuple[int, ...]) -> list[tuple[int, ...]]:
        out = []
        for a in range(7):
            for s in (1, -1):
                k = list(key)
                k[a] += s
                out.append(tuple(k))
        return out


@dataclass
class LevelResult:
    """Outcome of one level: best lattice key and cost, counts, the best cost after each expansion and every key
    seen with its cost (the origin's included; inf for keys outside the trust region, never scored)."""

    best_key: tuple[int, ...]
    best_cost: float
    expansions: int = 0
    renders: int = 0
    history: list[float] = field(default_factory=list)
    stopped: str = ""
    costs: dict[tuple[int, ...], float] = field(default_factory=dict)


def best_first(space, start_cost: float, score: Callable[[list[Pose]], np.ndarray],
               allowed: Callable[[Pose], bool], *, budget: int, patience: int, weight: float,
               depth_cost: float, pattern: bool = True) -> LevelResult:
    """Best-first search from the origin key; f = depth_cost * g + weight * h.

    Each expansion pops the open node of least f (ties broken by the integer key, so runs are reproducible),
    scores all its children not seen before (plus, with ``pattern``, the node two steps further along the
    move that reached it) in one batched call, and pushes them. A node's cost is never
    computed twice; children outside the trust region (``allowed`` False) are never scored nor expanded.
    The level stops after ``budget`` expansions, when the open list is empty, or after ``patience``
    consecutive expansions that did not lower the best cost (patience 0: never).
    """
    origin = (0,) * space.dim
    costs: dict[tuple[int, ...], float] = {origin: float(start_cost)}
    open_heap = [(weight * float(start_cost), origin, 0)]
    parent: dict[tuple[int, ...], tuple[int, ...]] = {}
    closed: set[tuple[int, ...]] = set()
    res = LevelResult(origin, float(start_cost))
    stale = 0
    while open_heap and res.expansions < budget:
        _, key, g = heapq.heappop(open_heap)
        if key in closed:
            continue
        closed.add(key)
        kids, poses = [], []
        cands = space.neighbours(key)
        if pattern and key in parent:  # pattern move: jump two more steps along the move that reached key
            jump = tuple(3 * a - 2 * b for a, b in zip(key, parent[key]))
            if jump not in cands:
                cands.append(jump)
        for k in cands:
            if k in costs:
                continue
            p = space.pose(k)
            if not allowed(p):
                costs[k] = math.inf
                continue
            kids.append(k)
            poses.append(p)
        c = score(poses) if poses else np.zeros(0)
        res.expansions += 1
        res.renders += len(poses)
        improved = False
        for k, ck in zip(kids, c):
            ck = float(ck)
            costs[k] = ck
            parent[k] = key
            heapq.heappush(open_heap, (depth_cost * (g + 1) + weight * ck, k, g + 1))
            if ck < res.best_cost:
                res.best_cost, res.best_key = ck, k
                improved = True
        res.history.append(res.best_cost)
        stale = 0 if improved else stale + 1
        if patience and stale >= patience:
            res.stopped = "no improvement"
            break
    if not res.stopped:
        res.stopped = "budget" if res.expansions >= budget else "open list empty"
    res.costs = costs
    return res
