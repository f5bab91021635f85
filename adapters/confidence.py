"""A localizer's own confidence in each pose, as a query's trust region and expected prior error.

ACE and GLACE write each pose's RANSAC inlier count (the 11th column of their pose files, CONVENTIONS §2), and
their error falls steeply with it. The tables below are, per inlier-count bin, the 99th percentile and the median
of ACE + GLACE's 7-Scenes errors against the SfM pGT (``../shared/data/poses/7scenes``; the test
``tests/test_prior_region.py`` recomputes them). :func:`inlier_region` turns a count into a trust region of
``REGION_MARGIN`` times its bin's 99th percentile, :func:`inlier_prior_error` into the bin's median error, and
:func:`inlier_trust` gives both as a ``QueryPrior``. Lengths are fractions of the query's median depth (measured
at 7-Scenes' typical 2 m), so the same image motion is allowed in any map's units. What they achieve:
``benchmarks/defaults.md``.
"""

from __future__ import annotations

import bisect
import math

from hgsloc_plugin.core.prior import QueryPrior

#: lower edges of the inlier-count bins
INLIER_EDGES = (0, 1000, 1500, 2000, 2500, 3000, 3500, 4000)
#: 99th percentile per bin of ACE + GLACE 7-Scenes errors against the SfM pGT: camera centre (cm), rotation (deg)
Q99_CM = (64.71, 12.00, 9.06, 5.15, 3.27, 3.28, 2.76, 2.42)
Q99_DEG = (7.58, 3.45, 2.38, 1.69, 1.02, 1.04, 0.86, 0.59)
#: median per bin of the same errors: camera centre (cm), rotation (deg)
MEDIAN_CM = (3.80, 2.20, 1.64, 1.23, 0.91, 0.89, 0.71, 0.62)
MEDIAN_DEG = (1.17, 0.56, 0.49, 0.39, 0.31, 0.27, 0.20, 0.16)
#: the region is this multiple of the bin's 99th percentile (wide enough that a prior within its bin's 99th
#: percentile is corrected without reaching the region's edge, where the acceptance rule refuses it)
REGION_MARGIN = 1.5
#: depth (m) at which Q99_CM was measured: 7-Scenes' typical median depth
REFERENCE_DEPTH = 2.0
#: pose-file dialects with an inlier count, and its token index
INLIER_COLUMN = {"ace": 10}


def inlier_region(inliers: float) -> tuple[float, float] | None:
    """The trust region for a pose with ``inliers`` RANSAC inliers.

    Returns:
        (max_shift_depth: the camera-shift bound as a fraction of the query's median depth, max_rotation_deg),
        or None when the count is unusable (not finite, negative; the default region applies).
    """
    i = _bin(inliers)
    return None if i is None else (REGION_MARGIN * Q99_CM[i] / 100.0 / REFERENCE_DEPTH, REGION_MARGIN * Q99_DEG[i])


def inlier_prior_error(inliers: float) -> tuple[float, float] | None:
    """The expected (median) error of a pose with ``inliers`` RANSAC inliers.

    Returns:
        (camera-centre error as a fraction of the query's median depth, rotation error in degrees), or None
        when the count is unusable.
    """
    i = _bin(inliers)
    return None if i is None else (MEDIAN_CM[i] / 100.0 / REFERENCE_DEPTH, MEDIAN_DEG[i])


def inlier_trust(inliers: float) -> QueryPrior:
    """The settings of a query whose pose has ``inliers`` RANSAC inliers: its trust region (``max_shift_depth``,
    ``max_rotation_deg``) and expected error (``prior_error_depth``, ``prior_error_deg``); none set when the
    count is unusable."""
    region, error = inlier_region(inliers), inlier_prior_error(inliers)
    if region is None or error is None:
        return QueryPrior()
    return QueryPrior(max_shift_depth=region[0], max_rotation_deg=region[1], prior_error_depth=error[0],
                      prior_error_deg=error[1])


def _bin(inliers: float) -> int | None:
    if not (math.isfinite(inliers) and inliers >= 0):
        return None
    return bisect.bisect_right(INLIER_EDGES, inliers) - 1


def record_inliers(dialect: str, tokens: list[str]) -> float | None:
    """The inlier count of a pose-file record, or None when its dialect has none (or it is not a number)."""
    col = INLIER_COLUMN.get(dialect)
    if col is None or len(tokens) <= col:
        return None
    try:
        return float(tokens[col])
    except ValueError:
        return None


#: hloc's 7-Scenes errors against the SfM pGT (``../shared/data/poses/7scenes/*/hloc.txt``, all 17,000 poses; the
#: test ``tests/test_prior_region.py`` recomputes them): median and 99th percentile, camera centre (cm) and degrees
HLOC_MEDIAN_CM, HLOC_MEDIAN_DEG = 1.10, 0.18
HLOC_Q99_CM, HLOC_Q99_DEG = 13.53, 2.45
#: below this many PnP inliers an hloc pose is taken as doubtful: the published 7-Scenes poses carry no counts, so
#: no table joins counts to errors; such a pose gets the widest ACE bin (a RANSAC pose from few inliers)
HLOC_FEW_INLIERS = 30


def hloc_trust(num_inliers: float) -> QueryPrior:
    """The settings of an hloc pose with ``num_inliers`` PnP inliers (hloc's ``<results>_logs.pkl``): at least
    ``HLOC_FEW_INLIERS``, hloc's own 7-Scenes median error as the expected error and ``REGION_MARGIN`` times its
    99th percentile as the trust region; fewer, the widest ACE inlier bin's; none set when the count is unusable.
    Lengths are fractions of the query's median depth, as :func:`inlier_trust`'s."""
    if not (math.isfinite(num_inliers) and num_inliers >= 0):
        return QueryPrior()
    if num_inliers < HLOC_FEW_INLIERS:
        return inlier_trust(0.0)
    scale = 1.0 / 100.0 / REFERENCE_DEPTH
    return QueryPrior(max_shift_depth=REGION_MARGIN * HLOC_Q99_CM * scale,
                      max_rotation_deg=REGION_MARGIN * HLOC_Q99_DEG, prior_error_depth=HLOC_MEDIAN_CM * scale,
                      prior_error_deg=HLOC_MEDIAN_DEG)
