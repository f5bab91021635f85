"""Levenberg-Marquardt polish of a pose on the ``cs`` cost, from the kernels' analytic pose derivatives.

Each iteration is one derivative pass (``Renderer.pose_gradient``: the cost, its gradient ``g`` and the Gauss-Newton
Hessian ``JtJ`` in the camera-frame increment ``xi = (w, v)``) at a trial pose. The step solves ``(JtJ + lambda
diag(JtJ)) xi = -g`` (Marquardt's scaling: rotation and translation need no common unit); a trial is kept only when
its cost is lower than the current pose's (keep-best), after which ``lambda`` shrinks; otherwise ``lambda`` grows
and the step is re-solved from the same system, damped until its image motion is at most ``RETRY_SHRINK`` of the
failed one's (a retry barely shorter fails again: near convergence ``lambda`` is tiny and ten times it changes
nothing). It stops when it has converged (``Convergence``: a step below ``step_px`` of image motion, times the
multiple the line search last needed, or a kept step that lowers the cost by less than ``decrease`` of it), after
``max_failures`` rejected trials in a row, or after ``iterations`` passes. A trial outside the trust region is not
rendered: the damping grows until the step fits (or the polish stops, "trust region"). A step whose line search
already shows a decrease under ``decrease`` is taken without its derivative pass (nothing would follow it): the
polish ends there, with the Hessian of the pose before it. A stage followed by a finer one likewise takes a kept
Gauss-Newton step under ``HANDOFF_PX`` without its pass and hands over (``Convergence.handoff_px``).

Direct trials: in the last stage (``Convergence.direct``) a step whose Gauss-Newton model predicts a decrease of at
least ``DIRECT_FROM`` times the convergence threshold goes straight to its derivative pass, which gives its cost too:
near the minimum the model's step is kept as it is, and its line-search render would only precede the pass. Only
while the model holds: after a failed trial, a kept step whose line search needed a longer multiple, a direct one
whose decrease says a longer step would have paid (:func:`longer_pays`), or a kept step that gained less than
``MIN_GAIN`` of the decrease its model predicted (the model overshoots), the next trials are line-searched until one
keeps its multiple 1 and gains as predicted. A step predicted to lower the cost less is still scored first: it
usually ends the stage without a pass.

Line search: before a derivative pass, the step's multiples ``LINE_SEARCH`` (1, 2, 4) are scored with the cost alone
(plain renders, ``Renderer.window_cost``) and the derivative pass goes to the best of them; when none lowers the
cost the trial fails without a derivative pass. The first multiple is scored alone, the others (one batch) only when
the parabola through the cost, its slope along the step (``g.xi``) and that render has its minimum beyond
``LONGER_FROM`` (1.5) steps, where 2 steps would beat 1 on it (:func:`longer_pays`). When the longest scored is the
best, the search goes on (``EXTEND``: 2 and 4 times it, one batch at a time, up to ``MAX_MULTIPLE``, inside the
trust region) while the cost falls, and the convergence test scales the next step by the multiple the last one
needed (a Gauss-Newton step far too short is not convergence; ``benchmarks/defaults.md``). A stage that starts
near its minimum scores ``FINE_LINE_SEARCH`` (1, 2) instead: there four times the step rarely wins
(``benchmarks/throughput.md``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..core.camera import Camera
from ..core.costs import cost_from_window
from ..core.pose import Pose
from ..render import RendererLike

LAMBDA0 = 1e-3
LAMBDA_MIN = 1e-7
LAMBDA_MAX = 1e6
MIN_DECREASE = 1e-4  # a kept step that lowers the cost by less than this fraction ends the polish
MAX_OUTSIDE = 12  # trials outside the trust region (each only raises the damping, no render)
LINE_SEARCH = (1.0, 2.0, 4.0)  # multiples of the step scored with the cost alone before a derivative pass
EXTEND = (2.0, 4.0)  # when the longest multiple is the best, the next ones (x its length), one batch at a time
MAX_MULTIPLE = 64.0
FINE_LINE_SEARCH = (1.0, 2.0)  # for a stage that starts near its minimum (after a coarser stage or the search)
# the longer multiples are scored only when the parabola through the cost, its slope along the step and the first
# multiple's cost has its minimum beyond this many first multiples (1.5: where 2 beats 1 on that parabola)
LONGER_FROM = 1.5
RETRY_SHRINK = 0.5  # after a failed trial, the next is at most this fraction of its image motion
MIN_STEP_PX = 0.01  # a step below this image motion (pixels at the polish size) ends the polish: converged
# ... and for a stage followed by a finer one (the gradient route's coarse sizes): the finer stage goes on
STAGE_STEP_PX = 0.25
HANDOFF_PX = 1.0  # ... which hands a kept Gauss-Newton step under this (pixels at its size) to the finer stage
# the last stage's trials predicted to lower the cost by this many times its ``decrease`` threshold (or more) skip
# the line search (``Convergence.direct``; how 2, 3 and 5 compare: ``benchmarks/defaults.md``)
DIRECT_FROM = 3.0
# ... and only after a kept step that gained at least this fraction of its model's predicted decrease: at 198x148 on
# snow_sharp every direct trial after a step gaining 0.09-0.57 of it raised the cost (a pass for nothing), every one
# after 0.69 or more lowered it (``benchmarks/defaults.md``)
MIN_GAIN = 0.6


@dataclass(frozen=True)
class Convergence:
    """When a polish stage has converged: a step under ``step_px`` of image motion (pixels at its size, times the
    multiple the line search last needed), or a kept step lowering the cost by less than ``decrease`` of it. A
    stage followed by a finer one also hands over (``handoff_px``): a Gauss-Newton step the line search keeps as
    it is (its multiple 1 wins) and under ``handoff_px`` of image motion is taken without its derivative pass, and
    the finer stage, which starts with one, goes on from there (0: never). A trial whose Gauss-Newton model predicts
    a decrease of at least ``direct`` times ``decrease`` of the cost goes to its derivative pass without a line
    search (0: never)."""

    step_px: float
    decrease: float
    handoff_px: float = 0.0
    direct: float = 0.0


FINAL = Convergence(MIN_STEP_PX, MIN_DECREASE, direct=DIRECT_FROM)  # the last stage
# a stage followed by a finer one; its decrease stays the last stage's: a coarser one (1e-2) saved 0.6 passes per
# query at 2 % / 1 deg but left a wide search's 32 px stage short of the basin on one 30 cm / 10 deg prior. Its
# handoff needs the multiple 1 to win: a stage crawling down a long valley in sub-pixel steps that the line search
# lengthens is not near its minimum (handing those over too left a 30 cm / 10 deg prior unfixed)
STAGE = Convergence(STAGE_STEP_PX, MIN_DECREASE, HANDOFF_PX)


@dataclass
class PolishStats:
    """One polish: where it ran, what it did and the curvature at its result.

    Attributes:
        width / height: scoring size of the polish.
        cost_start / cost: ``cs`` cost at that size, before and after.
        passes: derivative passes (each is one rendering with derivatives, about 3-10 renders' time).
        renders: plain renders of the line search.
        accepted_steps: trials that lowered the cost.
        step_px: image motion of the last accepted step (pixels at the polish size; 0 if none).
        stopped: "converged" (step below the threshold), "handoff" (to the finer stage: ``Convergence.handoff_px``),
            "no decrease", "iterations", "trust region".
        jtj: Gauss-Newton Hessian [6, 6] of the cost, in ``xi = (w [rad], v [scene units])``, at the returned pose
            or, when the last step was taken on its line-search cost alone, at the pose one negligible step before.
        grad: gradient [6] of the cost in ``xi`` from the same derivative pass as ``jtj``.
        cost_rendered: the cost of the returned pose from a plain render (the line search's,
            ``Renderer.window_cost``): the value a ``Scorer`` of ``cs`` at this size computes, bit for bit (``cost``
            may be the derivative pass's, whose arithmetic differs in the last bits); nan when not rendered.
    """

    width: int
    height: int
    cost_start: float
    cost: float
    passes: int
    accepted_steps: int
    renders: int
    step_px: float
    stopped: str
    jtj: np.ndarray
    grad: np.ndarray | None = None
    cost_rendered: float = math.nan

    def to_dict(self) -> dict:
        d = {k: v for k, v in vars(self).items() if k not in ("jtj", "grad")}
        d["jtj"] = np.asarray(self.jtj).round(8).tolist()
        return d


def step_pixels(xi: np.ndarray, f: float, depth: float) -> float:
    """Image motion in pixels of an increment ``xi`` [6]: rotation f |w| plus translation f |v| / depth."""
    return f * float(np.linalg.norm(xi[:3])) + f * float(np.linalg.norm(xi[3:])) / max(depth, 1e-12)


def predicted_decrease(g: np.ndarray, H: np.ndarray, xi: np.ndarray) -> float:
    """The decrease of the cost that the Gauss-Newton model (gradient ``g`` [6], Hessian ``H`` [6, 6]) predicts
    for the step ``xi`` [6]: ``-(g.xi + xi' H xi / 2)``."""
    return -(float(g @ xi) + 0.5 * float(xi @ H @ xi))


def longer_pays(drop: float, linear: float, longer_from: float) -> bool:
    """Whether a line search should score the multiples after its first: the parabola through the cost at the
    step's start, with the slope that predicts a decrease ``linear`` at the first multiple (``-g.xi`` times it),
    and through the decrease ``drop`` rendered there has its minimum beyond ``longer_from`` first multiples.
    False when the first multiple does not lower the cost (``drop <= 0``); True when it drops at least ``linear``
    (the parabola opens downwards or is a line)."""
    if not drop > 0:
        return False
    return drop >= linear or linear > 2.0 * longer_from * (linear - drop)


@dataclass
class Damping:
    """One polish's Levenberg-Marquardt state across its trials.

    Attributes:
        max_failures: trials in a row that did not lower the cost before the polish stops.
        lam: the damping added to the Hessian's diagonal (``LAMBDA_MIN`` to ``LAMBDA_MAX``).
        failures: trials in a row that did not lower the cost.
        retry_limit: image motion (pixels) the next trial must stay under (after a failed one; else inf).
        model_holds: the last trial's outcome followed the model (no failure, no longer multiple paying).
    """

    max_failures: int
    lam: float = LAMBDA0
    failures: int = 0
    retry_limit: float = math.inf
    model_holds: bool = True

    def more(self) -> bool:
        """More damping (x10, at most ``LAMBDA_MAX``); True when it is at the most."""
        self.lam = min(self.lam * 10.0, LAMBDA_MAX)
        return self.lam >= LAMBDA_MAX

    def failed(self, motion: float) -> bool:
        """A trial of ``motion`` pixels did not lower the cost: more damping, the next trial at most
        ``RETRY_SHRINK`` of it and line-searched (the model does not hold); True when that makes
        ``max_failures`` in a row (the polish stops)."""
        self.more()
        self.model_holds = False
        self.retry_limit = RETRY_SHRINK * motion
        self.failures += 1
        return self.failures >= self.max_failures

    def kept(self) -> None:
        """A trial lowered the cost and its step is kept: less damping (x0.1, at least ``LAMBDA_MIN``), no limit."""
        self.lam = max(self.lam * 0.1, LAMBDA_MIN)
        self.failures, self.retry_limit = 0, math.inf


def polish(renderer: RendererLike, camera: Camera, qstats, pose: Pose, *, depth: float, iterations: int,
           allowed: Callable[[Pose], bool], background=(0.0, 0.0, 0.0), mask_alpha: float = 0.0,
           converged: Convergence = FINAL, max_failures: int = 3,
           line_search: tuple[float, ...] = LINE_SEARCH, longer_from: float | None = LONGER_FROM
           ) -> tuple[Pose, PolishStats]:
    """Polish ``pose`` at ``camera``'s size against the query statistics ``qstats`` (``upload_window_query``).

    Args:
        depth: the scene's median depth in front of the camera (scales translations into pixels).
        iterations: derivative passes at most (the first, at ``pose``, included).
        allowed: the trust-region test.
        converged: the thresholds (``FINAL``; ``STAGE`` for a stage followed by a finer one).
        line_search: multiples of each step scored with the cost alone (``()``: none, every trial is a pass).
        longer_from: the multiples after the first are scored only when :func:`longer_pays` (None: always, with
            the first in one batch).

    Returns:
        (the best pose seen, its stats). The pose's cost is never above the start's.
    """
    f = 0.5 * (camera.fx + camera.fy)

    def evaluate(T: Pose):
        c, g, H = renderer.pose_gradient(camera, [T], qstats, background, mask_alpha)
        return float(c[0]), g[0], H[0]

    def multiples(ms, at: Pose, step: np.ndarray) -> list[tuple[float, Pose]]:
        return [(m, at.perturbed_in_camera(m * step[:3], m * step[3:])) for m in ms]

    def score(cands: list[tuple[float, Pose]]) -> np.ndarray:
        """Costs of line-search trials, from plain renders (counted in ``stats.renders``)."""
        stats.renders += len(cands)
        return cost_from_window(renderer.window_cost(camera, [T for _, T in cands], qstats, background, mask_alpha))

    cost, g, H = evaluate(pose)
    stats = PolishStats(camera.width, camera.height, cost, cost, 1, 0, 0, 0.0, "iterations", H)
    lm = Damping(max_failures)
    outside, reach = 0, 1.0
    while stats.passes < iterations:
        d = np.diag(H)
        A = H + lm.lam * np.diag(np.maximum(d, 1e-12 * max(float(d.max()), 1e-30)))
        try:
            xi = np.linalg.solve(A, -g)
        except np.linalg.LinAlgError:
            xi = np.full(6, np.nan)
        if not np.all(np.isfinite(xi)):
            stats.stopped = "no decrease"
            break
        motion = step_pixels(xi, f, depth)
        if motion * reach < converged.step_px:  # reach: the multiple the last kept step needed (GN steps run short)
            stats.stopped = "converged"
            break
        if motion > lm.retry_limit:  # a retry barely shorter than the failed trial would fail again: more damping
            if lm.more():
                stats.stopped = "no decrease"
                break
            continue
        trial = pose.perturbed_in_camera(xi[:3], xi[3:])
        if not allowed(trial):  # shorten the step (more damping) until it stays in the trust region
            at_most = lm.more()
            outside += 1
            if outside > MAX_OUTSIDE or at_most:
                stats.stopped = "trust region"
                break
            continue
        direct = (converged.direct > 0 and lm.model_holds
                  and predicted_decrease(g, H, xi) >= converged.direct * converged.decrease * cost)
        if direct:
            reach = 1.0
        elif line_search:
            first = line_search if longer_from is None else line_search[:1]
            cands = [(m, T) for m, T in multiples(first, pose, xi) if m == line_search[0] or allowed(T)]
            lc = score(cands)
            if (longer_from is not None and len(line_search) > 1
                    and longer_pays(cost - float(lc[0]), -float(g @ xi) * line_search[0], longer_from)):
                more = [(m, T) for m, T in multiples(line_search[1:], pose, xi) if allowed(T)]
                if more:
                    cands, lc = cands + more, np.concatenate([lc, score(more)])
            j = int(np.argmin(lc))
            if not lc[j] < cost:  # no multiple lowers the cost: a failed trial, no derivative pass
                if lm.failed(motion):
                    stats.stopped = "no decrease"
                    break
                continue
            longer = longer_from is None or len(cands) > 1  # else the first alone was scored: no extension
            while longer and j == len(cands) - 1 and cands[j][0] < MAX_MULTIPLE:  # the longest was best: go further
                more = [(m, T) for m, T in multiples([k * cands[j][0] for k in EXTEND], pose, xi) if allowed(T)]
                if not more:
                    break
                cands, lc = cands + more, np.concatenate([lc, score(more)])
                j2 = int(np.argmin(lc))
                if j2 == j:
                    break
                j = j2
            m, trial = cands[j]
            reach = m
            lm.model_holds = m == line_search[0]
            xi = m * xi
            motion = step_pixels(xi, f, depth)
            ends = None  # the step is taken on its rendered cost, without a derivative pass, and the stage ends
            if m == line_search[0] and motion < converged.handoff_px:
                ends = "handoff"  # the model holds: the finer stage goes on
            elif cost - lc[j] < converged.decrease * cost:
                ends = "converged"  # negligible: nothing would follow the pass
            if ends is not None:
                pose, cost = trial, float(lc[j])
                stats.cost_rendered = cost
                stats.accepted_steps += 1
                stats.step_px = motion
                stats.stopped = ends
                break
        rendered = float(lc[j]) if line_search and not direct else math.nan
        c2, g2, H2 = evaluate(trial)
        stats.passes += 1
        if c2 < cost:
            if direct:  # a longer step would have paid (the slope g.xi of the pose before): line-search the next
                lm.model_holds = not longer_pays(cost - c2, -float(g @ xi), LONGER_FROM)
            if lm.model_holds and not cost - c2 >= MIN_GAIN * predicted_decrease(g, H, xi):
                lm.model_holds = False  # the step gained much less than its model predicted: line-search the next
            negligible = cost - c2 < converged.decrease * cost
            pose, cost, g, H = trial, c2, g2, H2
            stats.cost_rendered = rendered
            stats.accepted_steps += 1
            stats.step_px = motion
            lm.kept()
            if negligible:
                stats.stopped = "converged"
                break
        elif lm.failed(motion):
            stats.stopped = "no decrease"
            break
    stats.cost, stats.jtj, stats.grad = cost, H, g
    if not math.isfinite(stats.cost):
        stats.stopped = "no decrease"
    return pose, stats
