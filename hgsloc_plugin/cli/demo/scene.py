"""A deterministic procedural room covered by Gaussians: the embedded default scene (no data files).

World frame: z up, metres. The room spans x, y in [-2.5, 2.5] and z in [0, 2.6]; its floor, ceiling and four
walls carry different textures (checkers, stripes, gradients, value noise, discs), and a few boxes stand in it,
so image differences constrain all six pose degrees of freedom. Colours use SH degree 1 with a weak view
dependence.
"""

from __future__ import annotations

import numpy as np

from ...core.pose import qvecs_to_rotmats, rotmat_to_qvec
from ...core.scene import SH_C0, GaussianScene

HALF = 2.5
HEIGHT = 2.6


def _value_noise(u, v, rng_seed, freq):
    rng = np.random.default_rng(rng_seed)
    g = rng.uniform(size=(freq + 2, freq + 2))
    x, y = u * freq, v * freq
    i, j = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - i, y - j
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    i, j = np.clip(i, 0, freq), np.clip(j, 0, freq)
    a = g[i, j] * (1 - fx) + g[i + 1, j] * fx
    b = g[i, j + 1] * (1 - fx) + g[i + 1, j + 1] * fx
    return a * (1 - fy) + b * fy


def _texture(kind: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """RGB [M, 3] in [0, 1] of texture ``kind`` at surface coordinates u, v in [0, 1]."""
    n1 = _value_noise(u, v, 100 + kind, 6)
    n2 = _value_noise(u, v, 200 + kind, 23)
    if kind == 0:  # floor: checkerboard with noise
        c = ((np.floor(u * 10) + np.floor(v * 10)) % 2)[:, None]
        rgb = c * np.array([0.85, 0.8, 0.7]) + (1 - c) * np.array([0.25, 0.2, 0.18])
    elif kind == 1:  # wall: vertical stripes over a gradient
        s = (np.sin(u * 2 * np.pi * 7) > 0)[:, None]
        rgb = np.stack([0.2 + 0.6 * v, 0.5 * np.ones_like(u), 0.8 - 0.5 * v], 1) * (0.6 + 0.4 * s)
    elif kind == 2:  # wall: discs on a noise background
        cu, cv = (u * 5) % 1 - 0.5, (v * 4) % 1 - 0.5
        d = (cu ** 2 + cv ** 2 < 0.09)[:, None]
        rgb = d * np.array([0.9, 0.3, 0.1]) + (1 - d) * np.stack([n1, 0.6 * n1 + 0.3, 0.4 * np.ones_like(u)], 1)
    elif kind == 3:  # wall: diagonal bands and colour ramp
        s = ((u * 6 + v * 3) % 1 < 0.5)[:, None]
        rgb = s * np.stack([0.2 * np.ones_like(u), 0.7 * u + 0.2, 0.4 + 0.5 * v], 1) + (1 - s) * np.array(
            [0.95, 0.9, 0.5])
    elif kind == 4:  # wall: grid of squares with noise colours
        gx, gy = np.floor(u * 8), np.floor(v * 5)
        h = (np.sin(gx * 12.9898 + gy * 78.233) * 43758.5453) % 1
        rgb = np.stack([h, (h * 7) % 1, (h * 13) % 1], 1) * 0.8 + 0.1
        edge = ((u * 8) % 1 < 0.08) | ((v * 5) % 1 < 0.08)
        rgb[edge] = 0.05
    else:  # ceiling / boxes: smooth noise
        rgb = np.stack([0.3 + 0.5 * n1, 0.3 + 0.4 * n2, 0.5 + 0.3 * n1 * n2], 1)
    rgb = rgb * (0.85 + 0.3 * n2[:, None])
    return np.clip(rgb, 0.02, 0.98)


def _plane(origin, eu, ev, size_u, size_v, spacing, kind, rng):
    """Gaussians on a rectangle origin + a*eu + b*ev, a in [0, size_u], b in [0, size_v]."""
    nu, nv = max(2, int(size_u / spacing)), max(2, int(size_v / spacing))
    a, b = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
    a = a.ravel() + rng.uniform(-0.3, 0.3, a.size) / nu
    b = b.ravel() + rng.uniform(-0.3, 0.3, b.size) / nv
    eu, ev = np.asarray(eu, float), np.asarray(ev, float)
    n = np.cross(eu, ev)
    means = np.asarray(origin, float) + np.outer(a * size_u, eu) + np.outer(b * size_v, ev)
    rgb = _texture(kind, np.clip(a, 0, 1), np.clip(b, 0, 1))
    R = np.stack([eu, ev, n], 1)  # columns: local axes in world
    q = rotmat_to_qvec(R)
    quats = np.tile(q, (len(means), 1))
    su, sv = size_u / nu, size_v / nv
    scales = np.column_stack([np.full(len(means), 0.7 * su), np.full(len(means), 0.7 * sv),
                              np.full(len(means), 0.05 * min(su, sv))])
    return means, quats, scales, rgb


def make_room_scene(seed: int = 0, density: float = 1.0) -> GaussianScene:
    """Build the room; ``density`` scales the number of Gaussians (1.0: about 40k)."""
    rng = np.random.default_rng(seed)
    sp = 0.045 / np.sqrt(density)
    H, Z = HALF, HEIGHT
    parts = [
        _plane([-H, -H, 0], [1, 0, 0], [0, 1, 0], 2 * H, 2 * H, sp, 0, rng),  # floor (normal +z)
        _plane([-H, H, Z], [1, 0, 0], [0, -1, 0], 2 * H, 2 * H, sp * 1.3, 5, rng),  # ceiling
        _plane([-H, H, 0], [1, 0, 0], [0, 0, 1], 2 * H, Z, sp, 1, rng),  # wall y = +H
        _plane([H, -H, 0], [-1, 0, 0], [0, 0, 1], 2 * H, Z, sp, 2, rng),  # wall y = -H
        _plane([H, H, 0], [0, -1, 0], [0, 0, 1], 2 * H, Z, sp, 3, rng),  # wall x = +H
        _plane([-H, -H, 0], [0, 1, 0], [0, 0, 1], 2 * H, Z, sp, 4, rng),  # wall x = -H
    ]
    # boxes: (centre x, y, size, height)
    for k, (bx, by, s, h) in enumerate([(1.2, 1.0, 0.6, 0.8), (-1.3, 0.9, 0.5, 1.2), (0.9, -1.4, 0.7, 0.5),
                                        (-1.0, -1.2, 0.4, 0.9)]):
        x0, x1, y0, y1 = bx - s / 2, bx + s / 2, by - s / 2, by + s / 2
        kind = 1 + k % 4
        parts += [
            _plane([x0, y0, h], [1, 0, 0], [0, 1, 0], s, s, sp, 5, rng),
            _plane([x0, y0, 0], [1, 0, 0], [0, 0, 1], s, h, sp, kind, rng),
            _plane([x1, y1, 0], [-1, 0, 0], [0, 0, 1], s, h, sp, kind, rng),
            _plane([x1, y0, 0], [0, 1, 0], [0, 0, 1], s, h, sp, (kind + 1) % 5, rng),
            _plane([x0, y1, 0], [0, -1, 0], [0, 0, 1], s, h, sp, (kind + 1) % 5, rng),
        ]
    means = np.concatenate([p[0] for p in parts])
    quats = np.concatenate([p[1] for p in parts])
    scales = np.concatenate([p[2] for p in parts])
    rgb = np.concatenate([p[3] for p in parts])
    n = len(means)
    sh = np.zeros((n, 4, 3), np.float32)
    sh[:, 0] = (rgb - 0.5) / SH_C0
    sh[:, 1:] = rng.normal(scale=0.04, size=(n, 3, 3))  # weak view dependence
    opac = rng.uniform(0.85, 0.98, n)
    return GaussianScene.from_arrays(means.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
                                     opac.astype(np.float32), sh=sh)


def densify(scene: GaussianScene, k: int, seed: int = 0) -> GaussianScene:
    """A map-scale stand-in: every Gaussian copied ``k`` times, centres jittered by half its largest scale,
    scales shrunk by 1 / sqrt(k) (so the surface looks the same with k times the Gaussians)."""
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    rng = np.random.default_rng(seed)
    n = scene.num_gaussians
    rep = np.repeat(np.arange(n), k)
    jitter = rng.normal(size=(n * k, 3)) * (0.5 * scene.scales.max(axis=1))[rep, None]
    return GaussianScene.from_arrays((scene.means[rep] + jitter).astype(np.float32), scene.quats[rep],
                                     (scene.scales[rep] / np.sqrt(k)).astype(np.float32), scene.opacities[rep],
                                     sh=scene.sh[rep])


def densify_split(scene: GaussianScene, k: int, seed: int = 0) -> GaussianScene:
    """A map-scale stand-in that renders as ``scene`` does: every Gaussian split into ``k`` children (``k`` = 1
    or >= 4), as 3DGS's densification splits one, with the parent's moments. Children's centres are ``k``
    points of zero mean and identity covariance (whitened normal draws, turned at random per parent) scaled
    by the parent's axes times ``sqrt(1 - 1/k)``; their scales are the parent's over ``sqrt(k)`` (a surface cut
    into ``k`` pieces), their opacity and colour the parent's: the mixture's mean and covariance are the
    parent's, and their summed footprint x opacity too."""
    if k == 1:
        return scene
    if k < 4:
        raise ValueError(f"k must be 1 or >= 4 (k points of identity covariance in 3-D), got {k}")
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(k, 3))
    z -= z.mean(axis=0)
    evals, evecs = np.linalg.eigh(z.T @ z / k)
    z = z @ evecs @ np.diag(evals ** -0.5) @ evecs.T  # mean 0, covariance I
    n = scene.num_gaussians
    q = rng.normal(size=(n, 4))
    turn = qvecs_to_rotmats(q / np.linalg.norm(q, axis=1, keepdims=True))  # [n, 3, 3]
    local = np.einsum("nij,kj->nki", turn, z)  # [n, k, 3]: the points turned per parent (covariance still I)
    R = qvecs_to_rotmats(scene.quats.astype(np.float64))
    offsets = np.einsum("nij,nkj->nki", R, local * scene.scales[:, None, :] * np.sqrt(1.0 - 1.0 / k))
    rep = np.repeat(np.arange(n), k)
    means = (scene.means[:, None, :] + offsets).reshape(-1, 3)
    return GaussianScene.from_arrays(means.astype(np.float32), scene.quats[rep],
                                     (scene.scales[rep] / np.sqrt(k)).astype(np.float32), scene.opacities[rep],
                                     sh=scene.sh[rep])
