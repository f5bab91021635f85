"""Whether a search result is trusted: the acceptance rule and the confidence of a refined pose.

A lower cost is not a better pose when the map is imperfect: on real photographs the cost minimum lies a
fraction of a pixel from the true pose, in a direction set by the map's errors. The rule therefore measures
every quantity against the cost's own scale at the solution, the **one-pixel rise** ``kappa``: the median
increase of the cost over the 12 lattice moves (+-1 px of image motion per rotation and translation axis,
rotations about the median-depth pivot) around the search's best pose, scored at the final resolution.

The search's pose is returned only when all hold (else the coarse pose, with the reason):
- ``"no improvement"``: its cost is not below the coarse pose's;
- ``"insignificant"``: the cost drop is below ``MIN_SIGNIFICANCE`` one-pixel rises (the coarse pose is
  already as good as the map can tell; measured on the real snow photos, starts at the true pose drop
  0.16-0.75 rises, starts 1 % of depth / 0.5 deg off drop 1.8-24);
- ``"weak alignment"``: ``kappa`` is below ``MIN_ALIGNMENT`` of the best cost itself (structural costs only:
  cs, ssim, ncc, whose level is comparable across images). Where the rendering lines up with the photo, one
  pixel of motion raises the cost by a clear fraction of it; where it lines up with nothing (a false basin,
  a prior beyond reach) the cost is flat at a high level. Measured (``benchmarks/trust.py``): accepted good
  results 1.5-4 % on the real snow photos and 14-80 % on the room; the two accepted results that ended
  worse than a 30 cm / 10 deg prior 0.2 % and 0.14 %;
- ``"flat valley"``: some axis move raises the cost by less than ``MIN_SHARPNESS`` of ``kappa`` (or lowers
  it): the pose is not pinned down along that axis (repetitive texture, textureless wall);
- ``"trust-region edge"``: it lies beyond ``EDGE_FRACTION`` of the trust region in shift or rotation (the
  search was stopped by the region, not by a minimum);
- ``"level inconsistency"``: the fine levels moved it further from the coarse levels' answer than
  ``MAX_LEVEL_SHIFT`` coarsest steps (the pyramid disagreed about the basin; on the lego and snow sets
  correct refinements move up to 4 steps after the coarse levels).

The **uncertainty** of a polished pose (:func:`pose_uncertainty`) is read from the Gauss-Newton Hessian ``H``
of the cs cost at the solution (``Renderer.pose_gradient``) and the cost's level ``c`` there: the covariance of
the increment ``xi = (w, v)`` is taken as ``UNCERTAINTY_SCALE^2 * c * H^-1`` (the least-squares form
``sigma^2 (J^T J)^-1`` with the residual level standing in for the noise; the factor, for residuals correlated
over the window and over the map's errors, is calibrated on real photographs: snow and lego, 33 refined
poses from 1-10 cm-equivalent priors: median |error| / sigma 0.85 for the camera centre and 0.58 for the
rotation, 1 of 33 centre errors beyond 2 sigma). On clean synthetic renders (the demo room) it overestimates
the error about 20x: pixel noise averages out, a real map's errors do not. It does not see a map's bias
(snow query 0: 2.9 cm-equivalent off, sigma 1.5).

When the prior's expected error is known (declared, or from a localizer's inlier count), the returned pose is
the **fusion** of the two (:func:`fuse_with_prior`): the posterior mean of the refined pose, with the covariance
above, and the prior, isotropic with a per-axis standard deviation of ``PRIOR_SPREAD`` times its median error.
Along the directions the image pins down the refined pose wins; along the map's weak directions, where its
minimum may be biased (snow query 0 drifts along the coupled rotation + sideways shift the cost cannot
separate), a precise prior holds. Measured (``benchmarks/trust.py``'s priors, scratch comparison of spreads
1.0 / 1.5 / 2.0 x the median / 1.54, the median of a 3D Gaussian's norm): at 2.0 no query of the snow, lego or
room rows with a declared or inlier-count error ended worse, and recall at 1 cm / 1 deg was at least the binary
rule's on every real-photo row; a narrower prior (1.0) gained more from 1 cm priors (snow 83 -> 100 %, lego
50 -> 83 %) but lost recall from Marepo-shaped priors with Marepo's median declared (snow 83 -> 44 %): a median
understates a heavy-tailed localizer's spread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..pose import Pose

MIN_SIGNIFICANCE = 1.0
#: per-axis standard deviation of a prior, in units of its expected (median) error; 2 / 1.54 (see above)
PRIOR_SPREAD = 1.3
MIN_SHARPNESS = 0.02
MIN_ALIGNMENT = 0.005
EDGE_FRACTION = 0.9
MAX_LEVEL_SHIFT = 6.0
UNCERTAINTY_SCALE = 0.1


def sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(sigma of the camera centre, sigma of the rotation in degrees) of a covariance [6, 6] of ``xi = (w, v)``:
    the root of the trace of each block (the centre moves by ``-R^T v``, a rotation, so its trace is ``v``'s)."""
    return (math.sqrt(max(float(np.trace(cov[3:, 3:])), 0.0)),
            math.degrees(math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0))))


def fuse_with_prior(pose: Pose, cov: np.ndarray, prior: Pose, prior_error: float | None,
                    prior_error_deg: float | None) -> tuple[Pose, np.ndarray]:
    """Posterior mean of a refined ``pose`` and the coarse ``prior`` (see the module docstring).

    Args:
        pose: the refined pose; cov: [6, 6] covariance of ``xi = (w, v)`` (``Pose.perturbed_in_camera``) at it.
        prior: the coarse pose; prior_error / prior_error_deg: its expected (median) error, camera centre in scene
            units and rotation in degrees; None: that part unknown (no pull in it).

    Returns:
        (fused pose, its covariance [6, 6]). In these coordinates the prior sits at ``xi_p = (log(R_p R^T),
        t_p - R_p R^T t)``, whose ``v`` is the camera-frame shift of the centre, so an isotropic prior on the
        centre and on the rotation is diagonal: ``xi = (P + C^-1)^-1 P xi_p`` with ``P`` the prior's information.
    """
    xp = pose.offset_in_camera(prior)
    info = np.zeros(6)
    if prior_error_deg is not None:
        info[:3] = (PRIOR_SPREAD * math.radians(prior_error_deg)) ** -2
    if prior_error is not None:
        info[3:] = (PRIOR_SPREAD * prior_error) ** -2
    post = np.linalg.inv(np.diag(info) + np.linalg.inv(cov))
    post = 0.5 * (post + post.T)
    xi = post @ (info * xp)
    return pose.perturbed_in_camera(xi[:3], xi[3:]), post


def pose_uncertainty(jtj: np.ndarray, cost: float) -> tuple[np.ndarray, float, float]:
    """Covariance and standard deviations of a polished pose (see the module docstring).

    Args:
        jtj: [6, 6] Gauss-Newton Hessian of the cs cost in ``xi = (w, v)`` (``Pose.perturbed_in_camera``) at the
            pose; cost: the cs cost there.

    Returns:
        (covariance [6, 6] of xi, sigma of the camera centre in scene units, sigma of the rotation in degrees);
        the sigmas are the root of the trace of the blocks (the centre moves by ``-R^T v``, a rotation, so its
        trace is ``v``'s). Infinite where ``jtj`` is singular or not finite.
    """
    H = 0.5 * (np.asarray(jtj, np.float64) + np.asarray(jtj, np.float64).T)
    if H.shape != (6, 6) or not np.all(np.isfinite(H)) or not (cost >= 0 and math.isfinite(cost)):
        return np.full((6, 6), math.inf), math.inf, math.inf
    ev = np.linalg.eigvalsh(H)
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return np.full((6, 6), math.inf), math.inf, math.inf
    cov = UNCERTAINTY_SCALE ** 2 * cost * np.linalg.inv(H)
    return (cov, *sigmas(cov))


@dataclass
class Assessment:
    """The acceptance rule's inputs and verdict for one query.

    Attributes:
        significance: (coarse cost - best cost) / kappa: the improvement in one-pixel rises.
        sharpness: smallest axis rise / kappa (<= 0: some 1-px move does not raise the cost).
        travel: largest of shift / max_shift and rotation / max_rotation from the coarse pose, in [0, 1].
        level_shift: distance between the coarse levels' best pose and the final one, in coarsest steps.
        kappa: median one-pixel rise of the cost at the best pose.
        alignment: kappa / best cost (nan when not checked).
        confidence: summary in [0, 1]: min(1, significance / 4) * min(1, sharpness / 0.1) * (1 - travel^4);
            0 when rejected.
        rejected: None when accepted, else the reason ("insignificant", "flat valley", ...).
    """

    significance: float
    sharpness: float
    travel: float
    level_shift: float
    kappa: float
    alignment: float
    confidence: float
    rejected: str | None

    def to_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in vars(self).items()}


def settled(a: Assessment) -> bool:
    """Whether a pose refused only for lack of improvement sits in a sharp, well-aligned minimum (every other
    test passes): the coarse pose is already as good as the map can tell, so a search from it is not run
    (``RefineConfig.gradient_first``)."""
    return (a.rejected in ("insignificant", "no improvement")
            and _shape_reason(a.alignment, a.sharpness, a.travel, a.level_shift, not math.isnan(a.alignment)) is None)


def _shape_reason(alignment: float, sharpness: float, travel: float, level_shift: float,
                  check_alignment: bool) -> str | None:
    """The rule's tests after the improvement ones, in order: the first that fails, or None."""
    if check_alignment and not alignment >= MIN_ALIGNMENT:
        return "weak alignment"
    if not sharpness >= MIN_SHARPNESS:
        return "flat valley"
    if travel > EDGE_FRACTION:
        return "trust-region edge"
    if level_shift > MAX_LEVEL_SHIFT:
        return "level inconsistency"
    return None


def assess(cost_initial: float, cost_best: float, rises: np.ndarray, travel: float, level_shift: float, *,
           check_alignment: bool = False) -> Assessment:
    """Apply the acceptance rule.

    Args:
        cost_initial / cost_best: the coarse pose's and the search's best cost at the final resolution.
        rises: [12] cost of each one-pixel axis move around the best pose minus ``cost_best``.
        travel: fraction of the trust region used (shift or rotation, the larger).
        level_shift: in coarsest-level steps.
        check_alignment: apply the "weak alignment" test (for the structural costs cs, ssim, ncc).
    """
    rises = np.asarray(rises, dtype=np.float64)
    kappa = float(np.median(rises)) if rises.size else math.nan
    drop = cost_initial - cost_best
    scale = kappa if kappa > 0 else math.inf
    significance = drop / scale
    sharpness = float(rises.min()) / scale if rises.size else math.nan
    alignment = kappa / cost_best if check_alignment and cost_best > 0 else math.nan
    if not drop > 0:
        reason = "no improvement"
    elif not significance >= MIN_SIGNIFICANCE:
        reason = "insignificant"
    else:
        reason = _shape_reason(alignment, sharpness, travel, level_shift, check_alignment)
    conf = 0.0
    if reason is None:
        conf = min(1.0, significance / 4.0) * min(1.0, sharpness / 0.1) * (1.0 - min(travel, 1.0) ** 4)
    return Assessment(float(significance), float(sharpness), float(travel), float(level_shift), kappa,
                      float(alignment), float(conf), reason)
