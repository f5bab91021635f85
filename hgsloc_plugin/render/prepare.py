"""Host-side preparation of a scene's Gaussians for the device: covariances, memory order, pose lists."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import taichi as ti

from ..core.pose import Pose, qvecs_to_rotmats
from ..core.scene import GaussianScene
from ..kernels.launch import empty
from ..kernels.launch import upload as upload_into


def covariances_3d(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Upper triangle of Sigma = R S S^T R^T per Gaussian: [N, 6] (xx, xy, xz, yy, yz, zz), float32.

    Args:
        quats: unit quaternions w, x, y, z [N, 4]; scales: [N, 3].
    """
    M = qvecs_to_rotmats(quats) * scales.astype(np.float64)[:, None, :]
    S = M @ M.transpose(0, 2, 1)
    return np.stack([S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]], 1).astype(np.float32)


def morton_order(means: np.ndarray, bits: int = 10) -> np.ndarray:
    """Permutation [N] that sorts centres [N, 3] along a Z-order curve over their bounding box (stable)."""
    m = np.asarray(means, np.float64)
    lo, hi = m.min(axis=0), m.max(axis=0)
    q = ((m - lo) / np.maximum(hi - lo, 1e-12) * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(m), np.uint64)
    for bit in range(bits):
        for a in range(3):
            code |= ((q[:, a] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + a)
    return np.argsort(code, kind="stable")


def as_pose_list(poses) -> tuple[list[Pose], bool]:
    """Normalise a Pose or a sequence of Poses; returns (list, was_single)."""
    if isinstance(poses, Pose):
        return [poses], True
    if isinstance(poses, Sequence) or hasattr(poses, "__iter__"):
        out = list(poses)
        for k, p in enumerate(out):
            if not isinstance(p, Pose):
                raise TypeError(f"poses[{k}] must be a Pose, got {type(p).__name__}")
        if not out:
            raise ValueError("poses is empty")
        return out, False
    raise TypeError(f"poses must be a Pose or a list of Poses, got {type(poses).__name__}")


def upload(a: np.ndarray, dtype) -> ti.Ndarray:
    """A host array as a device ndarray of ``dtype`` (same shape)."""
    a = np.ascontiguousarray(a)
    nd = empty(dtype, a.shape)
    upload_into(nd, a)
    return nd


@dataclass
class DeviceGaussians:
    """Gaussians resident on the device, float32, in resident order.

    Attributes:
        means [n, 3]; cov3d [n, 6] (xx, xy, xz, yy, yz, zz); opacities [n]; sh [n, K, 3]; smax [n] (largest
        scale: a bound on the standard deviation); source_index [n] (host): scene index of each resident
        Gaussian (-1: none, e.g. a merged level-of-detail Gaussian).
    """

    means: ti.Ndarray
    cov3d: ti.Ndarray
    opacities: ti.Ndarray
    sh: ti.Ndarray
    smax: ti.Ndarray
    source_index: np.ndarray

    FIELDS = ("means", "cov3d", "opacities", "sh", "smax")

    @property
    def n(self) -> int:
        return int(self.means.shape[0])

    @classmethod
    def from_scene(cls, scene: GaussianScene) -> DeviceGaussians:
        """The scene's Gaussians in Morton (Z-curve) order of their centres, so that the Gaussians of one tile sit
        close together in memory (the projection, sort and blend read them by index)."""
        o = morton_order(scene.means)
        return cls(upload(scene.means[o], ti.f32), upload(covariances_3d(scene.quats[o], scene.scales[o]), ti.f32),
                   upload(scene.opacities[o], ti.f32), upload(scene.sh[o], ti.f32),
                   upload(scene.scales[o].max(axis=1).astype(np.float32), ti.f32), o)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], source_index: np.ndarray) -> DeviceGaussians:
        """Gaussians from host arrays keyed by :attr:`FIELDS` (as from :meth:`to_arrays`), in the order given."""
        return cls(*(upload(arrays[k].astype(np.float32), ti.f32) for k in cls.FIELDS), np.asarray(source_index))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Host copies keyed by :attr:`FIELDS`."""
        return {k: getattr(self, k).to_numpy() for k in self.FIELDS}
