"""Derivative blending: the colour, alpha and pose derivatives of each pixel, in two layouts.

Front-to-back compositing (the tests of ``blend.shade``, so colour and alpha equal the image kernels') carrying
the derivatives in the pose increment ``xi`` [6] (``pose_grad``): per contributing Gaussian ``dsigma`` from its
record's derivatives, ``dalpha = -alpha dsigma`` (0 where alpha is capped at ``alpha_max``), ``dC += c (dalpha T +
alpha dT)``, ``dT' = dT (1 - alpha) - T dalpha`` (:func:`chain_step`); output ``drgb = dC + dT background``
[B, H, W, 3 * 6]. The alpha threshold and the early stop are discontinuities; their derivative is taken as 0.

- ``blend_grad`` (the GPU layout): one task per pixel walks its tile's depth-ordered list, optionally skipping
  the entries whose pixel mask (``pose_grad.pixel_masks``) leaves it out; :func:`chain_step` as written.
- ``splat_grad`` (the CPU layout, ``RasterConfig.blend`` "splat"): one task per tile, each Gaussian of its list
  loading its record and derivatives once and visiting only the pixels of its alpha ellipse, as the image's splat
  blend does (``splat.splat_walk``); the same chain in fewer operations: ``dsigma`` from a quadratic in the
  pixel's column set up once a row (:func:`_row_derivatives`) and the transmittance's relative derivative
  ``u = dT / T`` (:func:`_add_colour_and_derivatives`). The two agree to float32 rounding.
Reference twin: ``tests/test_pose_grad.py`` (finite differences of ``tests/reference/render_torch.py`` in
float64; the two layouts against each other).
"""

import functools

import taichi as ti

from .blend import colour_of, tile_range
from .config import RasterConfig
from .footprint import SIGMA_MARGIN
from .grain import item, spread
from .layout import Rec
from .splat import splat_walk

NXI = 6  # pose parameters
DX, DY, DCA, DCB, DCC = 0, 1, 2, 3, 4  # quantity index in the records' derivatives (times NXI)


@ti.func
def chain_step(alpha, capped, T, dx, dy, ca, cb, cc, col, D, dT, dC):
    """One contributing Gaussian's step of the derivatives' front-to-back compositing at a pixel.

    alpha: its alpha there (``capped``: at ``alpha_max``, whose derivative is 0), T: the transmittance before it,
    dx, dy: its 2D mean minus the pixel centre, (ca, cb, cc): its conic, col [3]: its colour, D [5, 6]: its record's
    derivatives (rows DX, DY, DCA, DCB, DCC of ``dpacked``); dT [6], dC [3, 6]: the pixel's derivatives of
    transmittance and colour before it. Returns them after it."""
    na = 0.0 if capped else -alpha  # d alpha = -alpha d sigma; d sigma through the record's five quantities
    s_x = na * (ca * dx + cb * dy)
    s_y = na * (cc * dy + cb * dx)
    s_a = na * 0.5 * dx * dx
    s_b = na * dx * dy
    s_c = na * 0.5 * dy * dy
    for j in ti.static(range(NXI)):
        dal = s_x * D[DX, j] + s_y * D[DY, j] + s_a * D[DCA, j] + s_b * D[DCB, j] + s_c * D[DCC, j]
        dvis = dal * T + alpha * dT[j]
        for c in ti.static(range(3)):
            dC[c, j] += dvis * col[c]
        dT[j] = dT[j] * (1.0 - alpha) - T * dal
    return dT, dC


@ti.func
def record_derivatives(dpacked: ti.template(), b, g):
    """D [5, 6]: the derivatives of Gaussian ``g``'s record in pose ``b`` (``dpacked``'s, quantity-major)."""
    return ti.Matrix([[dpacked[b, g, q * NXI + j] for j in ti.static(range(NXI))] for q in ti.static(range(5))])


@functools.cache
def blend_grad_func(config: RasterConfig, masked: bool):
    """``blend_grad`` (a ti.func: one task per pixel, the GPU layout): colour [B, H, W, 3], alpha [B, H, W] and the
    colour's derivatives drgb [B, H, W, 3 * 6] (channel-major). Its tile lists are binned at
    ``config.grad_tile_size``; ``masked``: ``masks`` [>= M] u64 are ``pixel_masks``'s, else any u64 array (unread)."""
    alpha_max, alpha_min, t_eps, tile = config.alpha_max, config.alpha_min, config.t_eps, config.grad_tile_size

    @ti.func
    def blend_grad(
        packed: ti.template(),
        dpacked: ti.template(),
        tile_start: ti.template(),
        isect: ti.template(),
        isect_base: ti.template(),
        masks: ti.template(),
        background: ti.template(),
        tiles_x,
        tiles_y,
        num_poses,
        out_rgb: ti.template(),
        out_alpha: ti.template(),
        out_d: ti.template(),
    ):
        H = out_rgb.shape[1]
        W = out_rgb.shape[2]
        for b, py, px in ti.ndrange(num_poses, H, W):
            start, end = tile_range(b, (py // tile) * tiles_x + px // tile, tile_start, isect_base)
            fx = ti.cast(px, ti.f32) + 0.5
            fy = ti.cast(py, ti.f32) + 0.5
            T = 1.0
            C = ti.Vector([0.0, 0.0, 0.0])
            dT = ti.Vector([0.0] * NXI)
            dC = ti.Matrix.zero(ti.f32, 3, NXI)
            bit = ti.cast((py % tile) * tile + px % tile, ti.u64)
            for k in range(start, end):
                if ti.static(masked):
                    if (masks[k] >> bit) & ti.u64(1) == ti.u64(0):
                        continue  # the Gaussian cannot reach this pixel (pixel_masks)
                g = isect[k]
                dx = packed[b, g, Rec.X] - fx
                dy = packed[b, g, Rec.Y] - fy
                ca = packed[b, g, Rec.CA]
                cb = packed[b, g, Rec.CB]
                cc = packed[b, g, Rec.CC]
                sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                if sigma > packed[b, g, Rec.LIM] + SIGMA_MARGIN:
                    continue  # alpha < alpha_min for certain: skip the exponential (the exact test follows)
                raw = packed[b, g, Rec.OPACITY] * ti.exp(-sigma)
                alpha = ti.min(alpha_max, raw)
                if sigma < 0.0 or alpha < alpha_min:
                    continue
                next_T = T * (1.0 - alpha)
                if next_T <= t_eps:
                    break
                col = colour_of(packed, b, g)
                C += alpha * T * col
                dT, dC = chain_step(alpha, raw >= alpha_max, T, dx, dy, ca, cb, cc, col,
                                    record_derivatives(dpacked, b, g), dT, dC)
                T = next_T
            for c in ti.static(range(3)):
                out_rgb[b, py, px, c] = C[c] + T * background[c]
                for j in ti.static(range(NXI)):
                    out_d[b, py, px, c * NXI + j] = dC[c, j] + dT[j] * background[c]
            out_alpha[b, py, px] = 1.0 - T

    return blend_grad


@ti.func
def _colour_and_derivatives(packed: ti.template(), dpacked: ti.template(), b, g):
    """The derivative blend's per-Gaussian terms: colour [3] and G [5, 6], its record's derivatives D regrouped
    for :func:`_row_derivatives` (conic ca, cb, cc): ``ca Dx + cb Dy``, ``cb Dx + cc Dy``, ``Dcc / 2``, ``Dcb``,
    ``Dca / 2``."""
    D = record_derivatives(dpacked, b, g)
    ca, cb, cc = packed[b, g, Rec.CA], packed[b, g, Rec.CB], packed[b, g, Rec.CC]
    G = ti.Matrix.zero(ti.f32, 5, NXI)
    for j in ti.static(range(NXI)):
        G[0, j] = ca * D[DX, j] + cb * D[DY, j]
        G[1, j] = cb * D[DX, j] + cc * D[DY, j]
        G[2, j] = 0.5 * D[DCC, j]
        G[3, j] = D[DCB, j]
        G[4, j] = 0.5 * D[DCA, j]
    return colour_of(packed, b, g), G


@ti.func
def _row_derivatives(G, dy):
    """P [3, 6]: a Gaussian's sigma derivatives along a row at offset ``dy``, a quadratic in the pixel's ``dx``:
    ``dsigma = (ca dx + cb dy) Dx + (cc dy + cb dx) Dy + dx^2 Dca / 2 + dx dy Dcb + dy^2 Dcc / 2
    = P[0] + dx P[1] + dx^2 P[2]`` (G from :func:`_colour_and_derivatives`)."""
    P = ti.Matrix.zero(ti.f32, 3, NXI)
    for j in ti.static(range(NXI)):
        P[0, j] = dy * (G[1, j] + dy * G[2, j])
        P[1, j] = G[0, j] + dy * G[3, j]
        P[2, j] = G[4, j]
    return P


@ti.func
def _add_colour_and_derivatives(acc: ti.template(), p, col, P, alpha, capped, T, dx, dy, ca, cb, cc):
    """The derivative blend's pixel terms (accumulators ``acc``: T [npx], (colour [3], u = dT / T [6]) [npx, 9],
    dC [npx, 3 * 6] channel-major): the colour as the image's; the derivatives as :func:`chain_step`'s, carrying the
    transmittance's relative derivative ``u`` (``u' = u - dalpha / (1 - alpha)``, ``dC += T col (dalpha + alpha
    u)``: fewer operations a Gaussian) and ``dsigma`` from the row's quadratic P (:func:`_row_derivatives`)."""
    for c in ti.static(range(3)):
        acc[1][p, c] += alpha * T * col[c]
    na = 0.0 if capped else -alpha  # d alpha = -alpha d sigma (0 where alpha is capped)
    r = -1.0 / (1.0 - alpha)
    tc = T * col
    for j in ti.static(range(NXI)):
        dal = na * (P[0, j] + dx * (P[1, j] + dx * P[2, j]))
        u = acc[1][p, 3 + j]
        t = dal + alpha * u
        for c in ti.static(range(3)):
            acc[2][p, c * NXI + j] += t * tc[c]
        acc[1][p, 3 + j] = u + dal * r


@functools.cache
def splat_grad_func(config: RasterConfig):
    """``splat_grad`` (a ti.func: one task per pose and tile, the CPU layout): the outputs of ``blend_grad``, with
    the same arguments (``masks`` unread). ``splat.splat_walk`` with the derivative terms: each Gaussian of the
    tile's list (depth order) loads its record and derivatives once and visits only the pixels of its alpha ellipse;
    the pixels' accumulators live in local arrays (``splat.splat_walk``). Per pixel the Gaussians and their order are
    ``blend_grad``'s, so colour, alpha and derivatives equal it to float32 rounding (the alphas along a row come
    from ``splat.row_factors``' recurrence; the compiler may fuse the multiply-adds differently)."""
    tile = config.grad_tile_size
    walk = splat_walk(config, tile, _colour_and_derivatives, _add_colour_and_derivatives, _row_derivatives)
    npx, f32 = tile * tile, ti.f32

    @ti.func
    def splat_grad(
        packed: ti.template(),
        dpacked: ti.template(),
        tile_start: ti.template(),
        isect: ti.template(),
        isect_base: ti.template(),
        masks: ti.template(),
        background: ti.template(),
        tiles_x,
        tiles_y,
        num_poses,
        out_rgb: ti.template(),
        out_alpha: ti.template(),
        out_d: ti.template(),
    ):
        H = out_rgb.shape[1]
        W = out_rgb.shape[2]
        stride = ti.static(spread())  # one task per tile on the CPU (grain.py)
        nt = tiles_x * tiles_y
        for task in range(num_poses * nt * stride):
            is_item, b, t = item(task, stride, nt)
            if is_item:
                trans, cu = ti.Vector.zero(f32, npx), ti.Matrix.zero(f32, npx, 3 + NXI)
                dc = ti.Matrix.zero(f32, npx, 3 * NXI)
                x0, y0 = walk((trans, cu, dc), b, t, tiles_x, W, H, packed, dpacked, tile_start, isect, isect_base)
                for py in range(y0, ti.min(y0 + tile, H)):
                    for px in range(x0, ti.min(x0 + tile, W)):
                        p = (py - y0) * tile + (px - x0)
                        T = ti.abs(trans[p])
                        for c in ti.static(range(3)):
                            out_rgb[b, py, px, c] = cu[p, c] + T * background[c]
                            for j in ti.static(range(NXI)):
                                dtj = T * cu[p, 3 + j]  # dT = T u
                                out_d[b, py, px, c * NXI + j] = dc[p, c * NXI + j] + dtj * background[c]
                        out_alpha[b, py, px] = 1.0 - T

    return splat_grad
