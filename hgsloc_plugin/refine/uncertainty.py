"""The uncertainty of a polished pose, the confidence it gives, and its fusion with a prior of known error.

All in ``xi = (w, v)``, the camera-frame perturbation of ``Pose.perturbed_in_camera``: rotation first (radians),
then the translation's shift (scene units). A polished pose has two covariances. The rule's is a cluster-robust
sandwich over bands of image rows plus the map's floor (:func:`pose_uncertainty`): conservative, it weighs the
prior's distance and the fusion with a prior of known median error (the posterior mean, :func:`fuse_with_prior`),
and the confidence is the probability under it that the pose lies within 1 % of the depth and 1 degree of the
truth (:func:`within_tolerance`): where the bands disagree, the map explains the image badly, and the confidence
falls. The returned sigmas are the image's pixel noise plus the floor (:func:`pixel_noise_uncertainty`, carried
through a fusion by :func:`fused_covariance`). Where the factors come from: ``benchmarks/trials.md``,
``benchmarks/sigma.md``.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.pose import Pose

#: per-axis standard deviation of a prior, in units of its expected (median) error
PRIOR_SPREAD = 1.3
#: horizontal bands of image rows whose gradients the pose's covariance is made of (``pose_uncertainty``)
BANDS = 12
#: the map's floor in the covariance when none is measured (``Tuning.map_floor_depth`` / ``map_floor_deg``): camera
#: centre as a fraction of the median depth, and degrees (3-D sigmas)
FLOOR_DEPTH = 0.003
FLOOR_DEG = 0.1


def sigmas(cov: np.ndarray) -> tuple[float, float]:
    """(sigma of the camera centre, sigma of the rotation in degrees) of a covariance [6, 6] of ``xi = (w, v)``:
    the root of the trace of each block (the centre moves by ``-R^T v``, a rotation, so its trace is ``v``'s)."""
    return (math.sqrt(max(float(np.trace(cov[3:, 3:])), 0.0)),
            math.degrees(math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0))))


def _prior_information(prior_error: float | None, prior_error_deg: float | None) -> np.ndarray:
    """[6] the diagonal information of a prior of expected (median) error ``prior_error`` (scene units) and
    ``prior_error_deg``; 0 for an unknown part."""
    info = np.zeros(6)
    if prior_error_deg is not None:
        info[:3] = (PRIOR_SPREAD * math.radians(prior_error_deg)) ** -2
    if prior_error is not None:
        info[3:] = (PRIOR_SPREAD * prior_error) ** -2
    return info


def fuse_with_prior(pose: Pose, cov: np.ndarray, prior: Pose, prior_error: float | None,
                    prior_error_deg: float | None) -> tuple[Pose, np.ndarray]:
    """Posterior mean of a refined ``pose`` and the coarse ``prior``.

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
    info = _prior_information(prior_error, prior_error_deg)
    post = np.linalg.inv(np.diag(info) + np.linalg.inv(cov))
    post = 0.5 * (post + post.T)
    xi = post @ (info * xp)
    return pose.perturbed_in_camera(xi[:3], xi[3:]), post


#: the tolerance the confidence of a polished pose is the probability of: camera centre within this fraction of the
#: median depth (1 %: 2 cm at 7-Scenes' 2 m) and rotation within ``CONFIDENT_DEG`` degrees
CONFIDENT_DEPTH = 0.01
CONFIDENT_DEG = 1.0


def _chi3_cdf(x: float) -> float:
    """P(chi-square with 3 degrees of freedom <= x)."""
    if not x > 0:
        return 0.0
    if math.isinf(x):
        return 1.0
    return math.erf(math.sqrt(x / 2.0)) - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)


def within_tolerance(sigma_t: float, sigma_r_deg: float, depth: float) -> float:
    """The probability, under a pose's own uncertainty (3-D sigmas: roots of the covariance blocks' traces, taken
    isotropic), that its centre lies within ``CONFIDENT_DEPTH`` of the depth and its rotation within
    ``CONFIDENT_DEG`` of the truth; 0 when a sigma is not finite."""
    if not (math.isfinite(sigma_t) and math.isfinite(sigma_r_deg)):
        return 0.0
    p_t = 1.0 if sigma_t <= 0 else _chi3_cdf(3.0 * (CONFIDENT_DEPTH * depth / sigma_t) ** 2)
    p_r = 1.0 if sigma_r_deg <= 0 else _chi3_cdf(3.0 * (CONFIDENT_DEG / sigma_r_deg) ** 2)
    return p_t * p_r


def _infinite() -> tuple[np.ndarray, float, float]:
    return np.full((6, 6), math.inf), math.inf, math.inf


def _sandwich(jtj: np.ndarray, meat: np.ndarray, depth: float, floor_depth: float,
              floor_deg: float) -> tuple[np.ndarray, float, float]:
    """``H^-1 meat H^-1`` plus the map's floor, with its sigmas; infinite where ``jtj`` is singular or not finite."""
    H = 0.5 * (np.asarray(jtj, np.float64) + np.asarray(jtj, np.float64).T)
    if H.shape != (6, 6) or not np.all(np.isfinite(H)) or not np.all(np.isfinite(meat)):
        return _infinite()
    ev = np.linalg.eigvalsh(H)
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return _infinite()
    Hi = np.linalg.inv(H)
    cov = Hi @ meat @ Hi
    floor = [math.radians(floor_deg) ** 2 / 3.0] * 3 + [(floor_depth * depth) ** 2 / 3.0] * 3
    cov = 0.5 * (cov + cov.T) + np.diag(floor)
    return (cov, *sigmas(cov))


def pose_uncertainty(jtj: np.ndarray, band_grads: np.ndarray, depth: float, floor_depth: float = FLOOR_DEPTH,
                     floor_deg: float = FLOOR_DEG) -> tuple[np.ndarray, float, float]:
    """The rule's covariance of a polished pose, cluster-robust over bands of image rows (what the prior's distance
    and the fusion weigh by).

    The pose minimises a sum of per-band costs; how far each band's gradient pulls at the minimum is what the
    residuals the map cannot explain (its own errors, lighting, occluders, a wrong minimum) do to the pose, in
    whatever units the image has: the sandwich ``H^-1 (K / (K - 6) sum_c g_c g_c^T) H^-1`` over the ``K`` bands
    (``BANDS``), plus the map's floor (``floor_depth`` of the depth and ``floor_deg``, isotropic 3-D sigmas) that no
    band sees. It errs wide: on a perfect map the bands' pulls cancel in their sum and it is 4-6x the error
    (``benchmarks/sigma.md``); the returned sigma is :func:`pixel_noise_uncertainty`'s.

    Args:
        jtj: [6, 6] Gauss-Newton Hessian of the cs cost in ``xi = (w, v)`` (``Pose.perturbed_in_camera``) at the
            pose; band_grads: [K, 6] the cost's gradient per band at the same pose (``Scorer.gradient_noise``);
            depth: the query's median depth (scene units); floor_depth / floor_deg: the map's floor
            (``Tuning.map_floor_depth`` / ``map_floor_deg``).

    Returns:
        (covariance [6, 6] of xi, sigma of the camera centre in scene units, sigma of the rotation in degrees);
        the sigmas are the root of the trace of the blocks (the centre moves by ``-R^T v``, a rotation, so its
        trace is ``v``'s). Infinite where ``jtj`` is singular or not finite, or with 6 bands or fewer.
    """
    G = np.asarray(band_grads, np.float64)
    if G.ndim != 2 or len(G) <= 6:
        return _infinite()
    return _sandwich(jtj, (G.T @ G) * (len(G) / (len(G) - 6.0)), depth, floor_depth, floor_deg)


def pixel_noise_uncertainty(jtj: np.ndarray, gradient_cov: np.ndarray, depth: float,
                            floor_depth: float = FLOOR_DEPTH,
                            floor_deg: float = FLOOR_DEG) -> tuple[np.ndarray, float, float]:
    """The covariance a polished pose is returned with: the image's pixel noise plus the map's floor.

    ``H^-1 C H^-1``, with ``C`` the cs gradient's covariance under independent noise in the query's pixels, each
    pixel's variance read off the residual the map leaves there (``render/gradient_noise.py``), plus the floor: what
    moves a whole view coherently (the map's errors, exposure) is not independent between pixels, and is measured on
    views with known poses (``hgsloc check --measure-floor``). Arguments and returns as :func:`pose_uncertainty`'s,
    with ``gradient_cov`` [6, 6] for the bands; infinite where ``jtj`` is singular or either is not finite.
    """
    C = np.asarray(gradient_cov, np.float64)
    if C.shape != (6, 6):
        return _infinite()
    return _sandwich(jtj, C, depth, floor_depth, floor_deg)


def fused_covariance(cov: np.ndarray, weighed_by: np.ndarray, prior_error: float | None,
                     prior_error_deg: float | None) -> np.ndarray:
    """The covariance [6, 6] of :func:`fuse_with_prior`'s pose when the fusion weighed the refined pose by the
    covariance ``weighed_by`` [6, 6] and its error has the covariance ``cov`` [6, 6]: ``K cov K^T + post P post``,
    with ``P`` the prior's information, ``post = (P + weighed_by^-1)^-1`` and ``K = post weighed_by^-1`` (``post``
    itself when ``cov`` is ``weighed_by``). prior_error / prior_error_deg: as for :func:`fuse_with_prior`."""
    info = _prior_information(prior_error, prior_error_deg)
    w_inv = np.linalg.inv(weighed_by)
    post = np.linalg.inv(np.diag(info) + w_inv)
    K = post @ w_inv
    out = K @ cov @ K.T + post @ np.diag(info) @ post
    return 0.5 * (out + out.T)


def prior_distance(pose: Pose, cov: np.ndarray, prior: Pose) -> float:
    """Mahalanobis distance of ``prior`` from ``pose`` under ``pose``'s covariance ``cov`` [6, 6] of ``xi = (w, v)``
    (``Pose.perturbed_in_camera``): how many of its own standard deviations the refinement moved the pose; inf
    where ``cov`` is not finite or singular (nothing to compare with: the rule's other tests decide)."""
    cov = np.asarray(cov, np.float64)
    if not np.all(np.isfinite(cov)):
        return math.inf
    xp = np.asarray(pose.offset_in_camera(prior), np.float64)
    try:
        return float(math.sqrt(max(float(xp @ np.linalg.solve(cov, xp)), 0.0)))
    except np.linalg.LinAlgError:
        return math.inf
