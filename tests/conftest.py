"""Shared fixtures: small random scenes, the ../shared data folder, Taichi on the CPU."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("HGSLOC_ARCH", "cpu")


def _share_cores() -> None:
    """Under pytest-xdist, each worker process (and the CLI processes it starts) takes its share of the cores for
    Taichi and torch: two workers of two threads each on two cores wait on each other's threads at every parallel
    loop's join (the suite ran about 10 % slower)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        share = max(1, (os.cpu_count() or 1) // workers)
        os.environ.setdefault("HGSLOC_CPU_THREADS", str(share))
        import torch

        torch.set_num_threads(int(os.environ["HGSLOC_CPU_THREADS"]))


_share_cores()

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test saying which path was missing."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not found: {p}")
    return p


def random_scene(n=400, sh_degree=1, seed=0, spread=1.0, centre=(0.0, 0.0, 3.0)):
    """A seeded random scene in front of a camera at the origin looking down +z."""
    from hgsloc_plugin import GaussianScene

    rng = np.random.default_rng(seed)
    means = rng.normal(size=(n, 3)) * spread * np.array([1.0, 0.75, 0.5]) + np.asarray(centre)
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(-3.5, -1.5, size=(n, 3))) * spread
    opac = rng.uniform(0.05, 0.99, size=n)
    k = (sh_degree + 1) ** 2
    sh = rng.normal(scale=0.3, size=(n, k, 3))
    sh[:, 0] = rng.uniform(-1.5, 1.5, size=(n, 3))
    return GaussianScene.from_arrays(means, quats, scales, opac, sh=sh)


def room_query(cam, pose_seed: int, noise_deg: float, noise_shift: float, noise_seed: int, density: float = 0.35):
    """The demo room, one of its query poses, that pose's rendering at ``cam`` and a prior ``noise_deg`` /
    ``noise_shift`` off it: (scene, true pose, image [H, W, 3], prior)."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.noise import se3_noise

    scene = make_room_scene(density=density)
    gt = query_poses(1, seed=pose_seed)[0]
    return scene, gt, hp.render(scene, cam, gt), se3_noise(gt, noise_deg, noise_shift,
                                                          np.random.default_rng(noise_seed))


@pytest.fixture(scope="package")  # tests/ is one package: read once per run
def donut():
    from hgsloc_plugin import GaussianScene

    return GaussianScene.from_ply(shared_path("scenes", "donut.ply"))


@pytest.fixture(scope="package")  # tests/ is one package: read once per run
def small_sh3():
    from hgsloc_plugin import GaussianScene

    return GaussianScene.from_ply(shared_path("scenes", "small_sh3.ply"))


class FakeScorer:
    """A scorer of known costs for the rule's tests: ``cost(poses) -> [B]`` is called per batch (each batch kept in
    ``batches``), and ``gradient_noise`` returns ``jtj`` [6, 6] with 12 band gradients whose cluster-robust meat is
    ``scale * jtj`` and the pixel-noise covariance ``noise_scale * jtj`` (default ``scale``), so the pose's
    covariances (``uncertainty.pose_uncertainty``, ``pixel_noise_uncertainty``) are ``scale * jtj^-1`` and
    ``noise_scale * jtj^-1`` plus the map's floor."""

    def __init__(self, cost, jtj, scale=1.0, noise_scale=None):
        self.cost, self.jtj, self.scale, self.batches = cost, np.asarray(jtj, np.float64), scale, []
        self.noise_scale = scale if noise_scale is None else noise_scale

    def __call__(self, poses):
        self.batches.append(list(poses))
        return np.asarray(self.cost(list(poses)), np.float64)

    def remember(self, pose, cost, metric):
        pass

    def gradient_noise(self, pose, bands):
        w, v = np.linalg.eigh(0.5 * (self.jtj + self.jtj.T)) if np.all(np.isfinite(self.jtj)) else (None, None)
        if w is None:
            return self.jtj, np.zeros((12, 6)), np.zeros((6, 6))
        root = v * np.sqrt(np.clip(w, 0.0, None))  # root @ root.T == jtj
        g = 0.5 * np.sqrt(self.scale) * np.vstack([root.T, root.T])  # [12, 6]: g.T g = scale (12 - 6) / 12 jtj
        return self.jtj, g, self.noise_scale * self.jtj
