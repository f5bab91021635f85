"""Independent PyTorch reference of the 3DGS forward pass (CPU), for testing the Taichi kernels.

Projection and SH come from gsplat's pure-PyTorch ``gsplat.cuda._torch_impl`` (1.5.3); the opacity-aware
radius, tile binning and blending are written here from CONVENTIONS §6, vectorised per tile in float64.
Twins: ``project`` <-> kernels/projection.py, ``bin_tiles`` <-> kernels/tile_sort.py, ``blend`` <-> kernels/blend.py.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from gsplat.cuda import _torch_impl as gs

ALPHA_MIN = 1.0 / 255.0


def project(scene, camera, viewmat_44: np.ndarray, eps2d=0.3, near=0.01, far=1e10, tile=16, dtype=torch.float32,
            fixed_filter: torch.Tensor | None = None):
    """Project one view. Returns a dict of tensors over the N Gaussians (radius 0 = culled).

    ``dtype``: float32 like the kernels, or float64 (for finite differences of the pose). A camera of a reduced
    image (``camera.downsample`` r > 1) renders with the dilation ``eps2d / r^2`` and the reduction's triangle
    filter (variance 1/6 pixel^2) added to the 2D covariance, the opacity times ``sqrt(det(cov2d + dilation) /
    det(cov2d + dilation + filter))`` (the footprint's integral kept); ``fixed_filter`` [N]: use these factors
    instead (the derivative pass holds them fixed)."""
    means = torch.from_numpy(scene.means).to(dtype)
    quats = torch.from_numpy(scene.quats).to(dtype)
    scales = torch.from_numpy(scene.scales).to(dtype)
    opac = torch.from_numpy(scene.opacities).to(dtype)
    covars, _ = gs._quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    vm = torch.from_numpy(viewmat_44).to(dtype)[None]
    K = torch.from_numpy(camera.K).to(dtype)[None]
    W, H = camera.width, camera.height
    r = getattr(camera, "downsample", 1.0)
    dilation, filt = (eps2d, 0.0) if r == 1.0 else (eps2d / r ** 2, 1.0 / 6.0)
    _, means2d, depths, conics, _ = gs._fully_fused_projection(means, covars, vm, K, W, H, eps2d=dilation + filt,
                                                                near_plane=near, far_plane=far)
    means_c, covars_c = gs._world_to_cam(means, covars, vm)
    _, cov2d = gs._persp_proj(means_c, covars_c, K, W, H)
    cov2d = cov2d[0]
    factor = torch.ones_like(opac)
    if filt > 0.0:
        det0 = (cov2d[:, 0, 0] + dilation) * (cov2d[:, 1, 1] + dilation) - cov2d[:, 0, 1] ** 2
        det1 = (cov2d[:, 0, 0] + dilation + filt) * (cov2d[:, 1, 1] + dilation + filt) - cov2d[:, 0, 1] ** 2
        factor = torch.sqrt(det0.clamp(min=0) / det1) if fixed_filter is None else fixed_filter.to(dtype)
        opac = opac * factor
    cov2d = cov2d + torch.eye(2, dtype=dtype) * (dilation + filt)
    means2d, depths, conics = means2d[0], depths[0], conics[0]
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] ** 2
    extend = torch.clamp(torch.sqrt(2.0 * torch.log(torch.clamp(opac, min=1e-30) / ALPHA_MIN).clamp(min=0)),
                         max=3.33)
    rx = torch.ceil(extend * torch.sqrt(cov2d[:, 0, 0].clamp(min=0)))
    ry = torch.ceil(extend * torch.sqrt(cov2d[:, 1, 1].clamp(min=0)))
    valid = (depths >= near) & (depths <= far) & (det > 0) & (opac >= ALPHA_MIN) & ~((rx <= 0) & (ry <= 0))
    valid &= (means2d[:, 0] + rx > 0) & (means2d[:, 0] - rx < W) & (means2d[:, 1] + ry > 0) & (means2d[:, 1] - ry < H)
    R = torch.from_numpy(viewmat_44[:3, :3]).double()
    campos = -R.T @ torch.from_numpy(viewmat_44[:3, 3]).double()
    dirs = (torch.from_numpy(scene.means).double() - campos).to(dtype)
    sh = torch.from_numpy(scene.sh).to(dtype)
    colors = torch.clamp(gs._spherical_harmonics(scene.sh_degree, dirs, sh) + 0.5, min=0.0)
    tx, ty = math.ceil(W / tile), math.ceil(H / tile)
    x0 = torch.clamp(torch.floor((means2d[:, 0] - rx) / tile), 0, tx).long()
    x1 = torch.clamp(torch.ceil((means2d[:, 0] + rx) / tile), 0, tx).long()
    y0 = torch.clamp(torch.floor((means2d[:, 1] - ry) / tile), 0, ty).long()
    y1 = torch.clamp(torch.ceil((means2d[:, 1] + ry) / tile), 0, ty).long()
    valid &= (x1 > x0) & (y1 > y0)
    return dict(means2d=means2d, conics=conics, depths=depths, opac=opac, colors=colors, valid=valid,
                rect=torch.stack([x0, y0, x1, y1], 1), radius=torch.stack([rx, ry], 1), factor=factor)


def bin_tiles(proj, camera, tile=16):
    """Per tile, the Gaussian ids sorted by depth (stable, ties by index): list of LongTensors."""
    tx, ty = math.ceil(camera.width / tile), math.ceil(camera.height / tile)
    ids = torch.nonzero(proj["valid"]).flatten()
    order = torch.sort(proj["depths"][ids], stable=True).indices
    ids = ids[order]
    rect = proj["rect"][ids]
    out = []
    for t in range(tx * ty):
        cx, cy = t % tx, t // tx
        m = (rect[:, 0] <= cx) & (cx < rect[:, 2]) & (rect[:, 1] <= cy) & (cy < rect[:, 3])
        out.append(ids[m])
    return out


def blend(proj, lists, camera, background=(0.0, 0.0, 0.0), tile=16, alpha_max=0.999, t_eps=1e-4):
    """Front-to-back compositing per pixel (CONVENTIONS §6 step 7), vectorised per tile in float64.

    Returns (rgb [H, W, 3], alpha [H, W]) as float64 numpy arrays.
    """
    W, H = camera.width, camera.height
    tx = math.ceil(W / tile)
    rgb = np.zeros((H, W, 3))
    alpha_img = np.zeros((H, W))
    bg = torch.tensor(background, dtype=torch.float64)
    for t, g in enumerate(lists):
        x0, y0 = (t % tx) * tile, (t // tx) * tile
        xs = torch.arange(x0, min(x0 + tile, W), dtype=torch.float64) + 0.5
        ys = torch.arange(y0, min(y0 + tile, H), dtype=torch.float64) + 0.5
        py, px = torch.meshgrid(ys, xs, indexing="ij")
        P = px.numel()
        if len(g) == 0:
            rgb[y0:y0 + ys.numel(), x0:x0 + xs.numel()] = bg.numpy()
            continue
        m = proj["means2d"][g].double()
        c = proj["conics"][g].double()
        dx = m[None, :, 0] - px.reshape(-1, 1)
        dy = m[None, :, 1] - py.reshape(-1, 1)
        sigma = 0.5 * (c[None, :, 0] * dx * dx + c[None, :, 2] * dy * dy) + c[None, :, 1] * dx * dy
        a = torch.clamp(proj["opac"][g].double()[None] * torch.exp(-sigma), max=alpha_max)
        ok = (sigma >= 0) & (a >= ALPHA_MIN)
        a = torch.where(ok, a, torch.zeros_like(a))
        T_after = torch.cumprod(1 - a, dim=1)
        stop = ok & (T_after <= t_eps)
        dead = torch.cumsum(stop.to(torch.int32), dim=1) > 0
        a = torch.where(dead, torch.zeros_like(a), a)
        T_before = torch.cumprod(torch.cat([torch.ones(P, 1, dtype=a.dtype), 1 - a[:, :-1]], 1), dim=1)
        w = a * T_before
        col = w @ proj["colors"][g].double()
        T = torch.prod(1 - a, dim=1)
        out = col + T[:, None] * bg[None]
        rgb[y0:y0 + ys.numel(), x0:x0 + xs.numel()] = out.reshape(ys.numel(), xs.numel(), 3).numpy()
        alpha_img[y0:y0 + ys.numel(), x0:x0 + xs.numel()] = (1 - T).reshape(ys.numel(), xs.numel()).numpy()
    return rgb, alpha_img


def render_reference(scene, camera, pose, background=(0.0, 0.0, 0.0), dtype=torch.float32, fixed_filter=None):
    """Full reference render of one pose: (rgb [H, W, 3], alpha [H, W]) float64 (projection in ``dtype``;
    ``fixed_filter``: as :func:`project`)."""
    proj = project(scene, camera, pose.matrix(), dtype=dtype, fixed_filter=fixed_filter)
    lists = bin_tiles(proj, camera)
    return blend(proj, lists, camera, background)


C1, C2 = 0.01 ** 2, 0.03 ** 2


def _window_stats(r: torch.Tensor, q: torch.Tensor, sigma: float, radius: int):
    """Windowed means and (co)variances (mr, mq, s_rr, s_qq, s_rq), each [1, 3, H, W], of r, q [H, W, 3]: a 2D
    float64 convolution with the (2 radius + 1)^2 Gaussian, replicate padding (differentiable in r)."""
    import torch.nn.functional as F

    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    g = g / g.sum()
    k2 = (g[:, None] * g[None, :])[None, None].repeat(3, 1, 1, 1)
    r = r.permute(2, 0, 1)[None]
    q = q.permute(2, 0, 1)[None]

    def filt(t):
        return F.conv2d(F.pad(t, (radius,) * 4, mode="replicate"), k2, groups=3)

    mr, mq = filt(r), filt(q)
    return mr, mq, (filt(r * r) - mr * mr).clamp(min=0), (filt(q * q) - mq * mq).clamp(min=0), filt(r * q) - mr * mq


def window_map(r: torch.Tensor, q: torch.Tensor, luminance: bool = False, sigma: float = 1.5, radius: int = 5,
               gn_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Per-pixel channel-mean SSIM or cs [H, W] of tensors r, q [H, W, 3] (differentiable in r).

    ``gn_weight``: instead of cs, ``1 - gn_weight * (s_rr + s_qq - 2 s_rq)`` with this weight [1, 3, H, W] held
    (the Gauss-Newton form of kernels/window_grad.py's JtJ, whose second derivative in r is the JtJ's);
    ``cs_gauss_newton_weight`` gives it.
    """
    mr, mq, s_rr, s_qq, s_rq = _window_stats(r, q, sigma, radius)
    if gn_weight is None:
        v = (2 * s_rq + C2) / (s_rr + s_qq + C2)
    else:  # 1 - cs = (s_rr + s_qq - 2 s_rq) / den, with the weight on the numerator held
        v = 1 - (s_rr + s_qq - 2 * s_rq) * gn_weight
    if luminance:
        v = v * (2 * mr * mq + C1) / (mr * mr + mq * mq + C1)
    return v.mean(1)[0]


def cs_gauss_newton_weight(r: torch.Tensor, q: torch.Tensor, sigma: float = 1.5, radius: int = 5) -> torch.Tensor:
    """The Gauss-Newton weight max(cs, 0) / D [1, 3, H, W] at the rendering r (no gradient), D = s_rr + s_qq + C2
    cs's denominator: with N = s_rr + s_qq - 2 s_rq and N'' = D'', the second derivative of 1 - cs = N / D
    without the rank-two terms in N' and D' is N'' (1 / D - N / D^2) = N'' cs / D."""
    with torch.no_grad():
        _, _, s_rr, s_qq, s_rq = _window_stats(r, q, sigma, radius)
        den = s_rr + s_qq + C2
        return ((2 * s_rq + C2) / den).clamp(min=0) / den


def window_cost(rgb: np.ndarray, alpha: np.ndarray, query: np.ndarray, mask_alpha: float = 0.0,
                luminance: bool = False, sigma: float = 1.5, radius: int = 5) -> tuple[float, float]:
    """Twin of kernels/window.py: (sum over valid pixels of the channel-mean SSIM or cs, valid pixel count).

    Written as a 2D float64 convolution with an explicit (2 radius + 1)^2 Gaussian kernel and replicate padding
    (the kernel uses two separable float32 passes with clamped coordinates).
    """
    r = torch.from_numpy(np.asarray(rgb, np.float64))
    q = torch.from_numpy(np.asarray(query, np.float64))
    v = window_map(r, q, luminance, sigma, radius)
    valid = torch.from_numpy(np.asarray(alpha) >= mask_alpha)
    return float(v[valid].sum()), float(valid.sum())


def cs_system(r: np.ndarray, q: np.ndarray, J: np.ndarray, valid: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Twin of kernels/window_grad.py at one rendering r [H, W, 3] with derivative images J [H, W, 3, 6] against the
    query q [H, W, 3] over the ``valid`` pixels [H, W]: the cs cost ``1 - mean(window_map)``, its gradient per
    pixel [H, W, 6] (d cost / d r times J, by autograd) and the Gauss-Newton Hessian [6, 6] (J^T (d^2 cost_GN / d
    r^2) J, cost_GN holding ``cs_gauss_newton_weight``), all float64."""
    valid = torch.from_numpy(np.asarray(valid, bool))
    n = max(float(valid.sum()), 1.0)
    rt = torch.from_numpy(np.asarray(r, np.float64)).requires_grad_(True)
    qt = torch.from_numpy(np.asarray(q, np.float64))
    Jt = torch.from_numpy(np.asarray(J, np.float64))
    cost = 1 - window_map(rt, qt)[valid].sum() / n
    (dr,) = torch.autograd.grad(cost, rt)
    per_pixel = torch.einsum("hwc,hwck->hwk", dr, Jt).numpy()
    weight = cs_gauss_newton_weight(rt.detach(), qt)
    cost_gn = 1 - window_map(rt, qt, gn_weight=weight)[valid].sum() / n
    (dgn,) = torch.autograd.grad(cost_gn, rt, create_graph=True)
    H = np.zeros((6, 6))
    for i in range(6):
        (hv,) = torch.autograd.grad((dgn * Jt[..., i]).sum(), rt, retain_graph=True)
        H[i] = torch.einsum("hwc,hwck->k", hv, Jt).numpy()
    return float(cost.detach()), per_pixel, H


def cs_gradient_noise(r: np.ndarray, q: np.ndarray, J: np.ndarray, valid: np.ndarray, sigma: float = 1.5,
                      radius: int = 5) -> np.ndarray:
    """Twin of render/gradient_noise.py: the cs gradient's covariance [6, 6] under independent noise in the query
    q [H, W, 3], at the rendering r [H, W, 3] with derivative images J [H, W, 3, 6] over the ``valid`` pixels
    [H, W]. The influence of q on the gradient of ``1 - mean(window_map)`` with cs's denominator held
    (``gn_weight`` = 1 / D) comes from automatic differentiation twice (d/dq of d/dr, times J); each pixel's noise
    variance is its windowed residual squared over E[e^2] / s^2 of the 2-D window; all float64."""
    valid_t = torch.from_numpy(np.asarray(valid, bool))
    n = max(float(valid_t.sum()), 1.0)
    rt = torch.from_numpy(np.asarray(r, np.float64)).requires_grad_(True)
    qt = torch.from_numpy(np.asarray(q, np.float64)).requires_grad_(True)
    Jt = torch.from_numpy(np.asarray(J, np.float64))
    with torch.no_grad():
        mr, mq, s_rr, s_qq, _ = _window_stats(rt, qt, sigma, radius)
    cost = 1 - window_map(rt, qt, gn_weight=1.0 / (s_rr + s_qq + C2))[valid_t].sum() / n
    (dr,) = torch.autograd.grad(cost, rt, create_graph=True)
    grad = torch.einsum("hwc,hwck->k", dr, Jt)
    influence = torch.stack([torch.autograd.grad(grad[i], qt, retain_graph=True)[0] for i in range(6)], -1)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    g = g / g.sum()
    factor = 1 - 2 * g[radius] ** 2 + (g * g).sum() ** 2
    e = (rt.detach() - qt.detach()) - (mr - mq)[0].permute(1, 2, 0)
    weighted = (influence * e[..., None] / torch.sqrt(factor)).reshape(-1, 6)
    return (weighted.T @ weighted).numpy()
