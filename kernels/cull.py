"""Per-query working set: which Gaussians can reach any image rendered from a region of poses.

All poses of one query's search lie in a trust region around the coarse pose: camera centres within ``max_shift``
of its centre, rotations within ``max_rotation`` of its rotation. A Gaussian that no pose of that region can see is
culled by the projection kernel for every render of the search, so it can be dropped once per query. The
test is conservative (it never drops a Gaussian that some pose of the region would render) and uses only the
bounds the projection kernel itself obeys:

- the projection culls a Gaussian whose box ``[mx - rx, mx + rx]`` misses the image. With the Jacobian's
  off-axis term clamped to ``L`` (``projection.py``) and the 2D covariance ``J Sc J^T + w I`` (``w``: the
  camera's widening, ``eps2d`` or more: ``RasterConfig.widening``), the box
  half-extent in normalised image units is at most ``A / z + B`` with ``A = 3.33 sqrt(2 + Lx^2 + Ly^2) s_max``
  (``s_max``: the largest scale; 3.33 bounds both radius modes) and ``B = (3.33 sqrt(2 w + 0.32) + 1) / f``
  (dilation and the ceil to whole pixels). Multiplied by ``z > 0``, "the box reaches the image's right
  edge x/z <= X" becomes the linear condition ``(X + B) z - x >= -A`` on the camera-frame centre, i.e. the
  centre lies at most ``A / |n|`` outside a plane through the camera centre with normal
  ``n = (-1, 0, X + B)``; likewise for the other three edges, and ``z >= near`` for the near plane.
- for a pose of the region, the camera-frame centre is ``q' = R_d (q - d)`` with ``|d| <= max_shift`` and
  ``R_d`` a rotation by at most ``max_rotation``, ``q`` the centre in the coarse camera's frame. So
  ``n.q' = (R_d^T n).q - (R_d^T n).d <= |q| cos(max(0, phi - max_rotation)) + max_shift`` where ``phi`` is the
  angle between ``n`` and ``q``.

A Gaussian is dropped when that upper bound fails one of the five planes (no pose of the region sees it); it is
kept otherwise (and, in the gsplat radius mode, its opacity reaches ``alpha_min``, as the projection requires).
Since ``cos(max(0, phi - max_rotation)) >= cos(phi)``, the bound is at least ``n.q + max_shift``: a plane this
passes by a margin far above float64 rounding is passed without the angles, the others get the bound itself
(the same flags). Kept Gaussians keep their order, so depth ties resolve as in the full map and images rendered
from the working set equal those from the full map bit for bit. The reference is the projection kernel itself:
``tests/test_working_set.py`` checks that every Gaussian it keeps for poses on the region's edge is in the working
set, and the flags against a NumPy twin of the bound.
"""


import functools
import math

import taichi as ti

from .config import RasterConfig

NPLANES = 5  # right, left, bottom, top, near
EXTENT_SLACK = 1.01  # float32 rounding margin on both terms of the bound
#: relative margin of the test without angles: far above the float64 rounding of the angles' path
QUICK_MARGIN = 1e-6


def jacobian_limits(camera) -> tuple[float, float]:
    """The projection's clamps of |x / z| and |y / z| for one camera (``projection.py``: the image bounds plus
    0.3 of the half field of view)."""
    c = camera
    return (max((c.width - c.cx) / c.fx, c.cx / c.fx) + 0.15 * c.width / c.fx,
            max((c.height - c.cy) / c.fy, c.cy / c.fy) + 0.15 * c.height / c.fy)


def extent_coefficient(lim_x: float, lim_y: float) -> float:
    """``A / s_max``: the box half-extent's term in the largest scale, for Jacobian clamps ``lim_x``, ``lim_y``."""
    return 3.33 * math.sqrt(2.0 + lim_x * lim_x + lim_y * lim_y) * EXTENT_SLACK


def extent_pixels(config: RasterConfig, downsample: float = 1.0) -> float:
    """``B * f``: the box half-extent's constant term in pixels (the widening of a camera of ``downsample``,
    ``RasterConfig.widening``, at least ``eps2d``; ceil to whole pixels)."""
    widen = max(config.eps2d, sum(config.widening(downsample)))
    return (3.33 * math.sqrt(2.0 * widen + 0.32) + 1.0) * EXTENT_SLACK + 1e-3


@functools.cache
def keep_kernel(config: RasterConfig):
    """Compiled working-set test.

    Kernel arguments:
        means [N, 3], smax [N] (largest scale per Gaussian), opacities [N],
        viewmat [3, 4] (coarse world-to-camera), planes [5, 4] (unit normal n, offset o: a pose sees the
        Gaussian only if n . q' >= -o with ``o = A_factor * smax + o_const`` per plane, see ``planes()``),
        a_factor [5] (per plane, multiplies smax), max_shift, max_rotation (radians);
        output: keep [N] int32 (1 = in the working set).
    """
    alpha_min = config.alpha_min
    gsplat = config.radius_mode == "gsplat"

    @ti.kernel
    def keep(
        means: ti.types.ndarray(dtype=ti.f32, ndim=2),
        smax: ti.types.ndarray(dtype=ti.f32, ndim=1),
        opacities: ti.types.ndarray(dtype=ti.f32, ndim=1),
        viewmat: ti.types.ndarray(dtype=ti.f64, ndim=2),
        planes: ti.types.ndarray(dtype=ti.f64, ndim=2),
        a_factor: ti.types.ndarray(dtype=ti.f64, ndim=1),
        max_shift: ti.f64,
        max_rotation: ti.f64,
        out: ti.types.ndarray(dtype=ti.i32, ndim=1),
    ):
        for i in range(means.shape[0]):
            ok = 1
            if ti.static(gsplat):
                if opacities[i] < alpha_min:
                    ok = 0
            if ok:
                q = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
                for r in ti.static(range(3)):
                    q[r] = (viewmat[r, 0] * ti.cast(means[i, 0], ti.f64) + viewmat[r, 1] * ti.cast(means[i, 1], ti.f64)
                            + viewmat[r, 2] * ti.cast(means[i, 2], ti.f64) + viewmat[r, 3])
                d = q.norm()
                s = ti.cast(smax[i], ti.f64)
                for k in ti.static(range(NPLANES)):
                    if ok:
                        n = ti.Vector([planes[k, 0], planes[k, 1], planes[k, 2]])
                        nq = n.dot(q)
                        rhs = -(a_factor[k] * s + planes[k, 3])
                        # d cos(max(0, phi - max_rotation)) >= d cos(phi) = n.q: a centre this far inside the
                        # plane passes without the angles (the margin covers their rounding), the rest are tested
                        if nq + max_shift < rhs + QUICK_MARGIN * (d + max_shift + ti.abs(rhs)):
                            c = ti.cast(1.0, ti.f64)
                            if d > 0.0:
                                c = ti.min(1.0, ti.max(-1.0, nq / d))
                            ang = ti.max(0.0, ti.acos(c) - max_rotation)
                            if d * ti.cos(ang) + max_shift < rhs:
                                ok = 0
            out[i] = ok

    return keep


@functools.cache
def gather_kernel(ndim: int):
    """``dst[j, ...] = src[idx[j], ...]`` for float32 arrays of 1 to 3 dimensions."""

    if ndim == 1:
        @ti.kernel
        def gather1(src: ti.types.ndarray(dtype=ti.f32, ndim=1), idx: ti.types.ndarray(dtype=ti.i32, ndim=1),
                    dst: ti.types.ndarray(dtype=ti.f32, ndim=1)):
            for j in range(idx.shape[0]):
                dst[j] = src[idx[j]]

        return gather1
    if ndim == 2:
        @ti.kernel
        def gather2(src: ti.types.ndarray(dtype=ti.f32, ndim=2), idx: ti.types.ndarray(dtype=ti.i32, ndim=1),
                    dst: ti.types.ndarray(dtype=ti.f32, ndim=2)):
            for j in range(idx.shape[0]):  # one task per row: its inner loop a plain copy
                s = idx[j]
                for a in range(src.shape[1]):
                    dst[j, a] = src[s, a]

        return gather2
    if ndim == 3:
        @ti.kernel
        def gather3(src: ti.types.ndarray(dtype=ti.f32, ndim=3), idx: ti.types.ndarray(dtype=ti.i32, ndim=1),
                    dst: ti.types.ndarray(dtype=ti.f32, ndim=3)):
            for j in range(idx.shape[0]):
                s = idx[j]
                for a in range(src.shape[1]):
                    for c in range(src.shape[2]):
                        dst[j, a, c] = src[s, a, c]

        return gather3
    raise ValueError(f"gather_kernel: ndim must be 1, 2 or 3, got {ndim}")


def planes(cameras, config: RasterConfig) -> tuple[list[list[float]], list[float]]:
    """The five planes of :func:`keep_kernel` for every camera (``width``, ``height``, ``fx``, ``fy``, ``cx``,
    ``cy``, ``downsample``) the search renders with: the union of their image bounds in normalised coordinates,
    their largest Jacobian clamps (as ``projection.py`` computes them), their smallest focal length and their
    widest widening.

    Returns:
        (planes [5][4]: unit normal and constant offset, a_factor [5]: offset per unit of ``smax``).
    """
    x0 = min(-c.cx / c.fx for c in cameras)
    x1 = max((c.width - c.cx) / c.fx for c in cameras)
    y0 = min(-c.cy / c.fy for c in cameras)
    y1 = max((c.height - c.cy) / c.fy for c in cameras)
    lims = [jacobian_limits(c) for c in cameras]
    lx, ly = max(v[0] for v in lims), max(v[1] for v in lims)
    b = max(extent_pixels(config, c.downsample) for c in cameras) / min(min(c.fx, c.fy) for c in cameras)
    a = extent_coefficient(lx, ly)
    rows, fac = [], []
    for n in ((-1.0, 0.0, x1 + b), (1.0, 0.0, -(x0 - b)), (0.0, -1.0, y1 + b), (0.0, 1.0, -(y0 - b))):
        norm = math.sqrt(sum(v * v for v in n))
        rows.append([n[0] / norm, n[1] / norm, n[2] / norm, 0.0])
        fac.append(a / norm)
    rows.append([0.0, 0.0, 1.0, -config.near_plane])  # z' >= near
    fac.append(0.0)
    return rows, fac
