"""The Taichi renderer against the independent PyTorch reference (tests/reference/render_torch.py)."""

from __future__ import annotations

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.kernels import RasterConfig

from .conftest import random_scene
from .reference.render_torch import bin_tiles, project, render_reference, window_cost


def psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - b) ** 2))
    return 10 * np.log10(1.0 / max(mse, 1e-20))


def assert_matches(img, ref, label):
    p, mad = psnr(img, ref), float(np.abs(img - ref).mean())
    assert p >= 45.0 and mad <= 1e-3, f"{label}: PSNR {p:.2f} dB, mean abs diff {mad:.2e}"


DONUT_VIEWS = [
    ((0.25, -0.25, 0.25), (0.0, 0.0, 0.03)),
    ((-0.2, 0.05, 0.3), (0.01, 0.0, 0.02)),
    ((0.02, 0.3, 0.12), (0.0, 0.0, 0.04)),
]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_random_scene_matches_reference(seed, sh_degree):
    scene = random_scene(n=300, sh_degree=sh_degree, seed=seed)
    cam = hp.Camera(70, 45, 60.0, 62.0, 33.0, 24.5)  # off-centre principal point, W, H not multiples of 16
    T = hp.Pose.identity().perturbed_in_camera([0.02 * seed, -0.03, 0.01], [0.05, 0.0, -0.1 * seed])
    bg = (0.2, 0.5, 0.9) if seed == 1 else (0.0, 0.0, 0.0)
    rgb, alpha, _ = hp.render_full(scene, cam, T, background=bg)
    ref, ref_alpha = render_reference(scene, cam, T, background=bg)
    assert_matches(rgb, ref, f"seed {seed} deg {sh_degree}")
    assert np.abs(alpha - ref_alpha).max() < 1e-3


@pytest.mark.parametrize("view", range(len(DONUT_VIEWS)))
@pytest.mark.parametrize("size", [(160, 120), (64, 48)])
def test_donut_matches_reference(donut, view, size):
    eye, target = DONUT_VIEWS[view]
    cam = hp.Camera.from_fov(size[0], size[1], 50.0)
    T = hp.Pose.look_at(eye, target)
    bg = (1.0, 1.0, 1.0) if view == 1 else (0.0, 0.0, 0.0)
    rgb = hp.render(donut, cam, T, background=bg)
    ref, _ = render_reference(donut, cam, T, background=bg)
    assert rgb.std() > 0.05, "the view should show the object"
    assert_matches(rgb, ref, f"donut view {view} {size}")


def test_donut_640x480_matches_reference(donut):
    cam = hp.Camera.from_fov(640, 480, 50.0)
    T = hp.Pose.look_at(*DONUT_VIEWS[0])
    assert_matches(hp.render(donut, cam, T), render_reference(donut, cam, T)[0], "donut 640x480")


@pytest.mark.parametrize("view", [0, 1])
def test_small_sh3_matches_reference(small_sh3, view):
    c = np.median(small_sh3.means, axis=0)
    eye = c + (np.array([600.0, -500.0, 300.0]) if view == 0 else np.array([-300.0, 700.0, -200.0]))
    cam = hp.Camera(120, 96, 110.0, 110.0, 58.0, 50.0)
    T = hp.Pose.look_at(eye, c)
    rgb = hp.render(small_sh3, cam, T)
    ref, _ = render_reference(small_sh3, cam, T)
    assert rgb.std() > 0.01
    assert_matches(rgb, ref, f"small_sh3 view {view}")


def test_pixel_and_splat_blend_agree():
    scene = random_scene(n=500, sh_degree=2, seed=5)
    cam = hp.Camera(90, 60, 70.0, 70.0, 45.0, 30.0)
    poses = [hp.Pose.identity().perturbed_in_camera([0, 0.01 * k, 0], [0.02 * k, 0, 0]) for k in range(3)]
    a = hp.render(scene, cam, poses, config=RasterConfig(blend="pixel"))
    b = hp.render(scene, cam, poses, config=RasterConfig(blend="splat"))
    assert np.abs(a - b).max() < 1e-5


def test_tile_lists_match_reference_binning():
    """The kernel's per-tile lists (ids and depth order) equal the reference binning (no exact depth ties here,
    so the resident order does not matter). The reference bins by box: so does the renderer here (CUDA's
    default bins by ellipse, ``tests/test_tile_sort.py`` checks that)."""
    from hgsloc_plugin.render import get_renderer, read_rows

    scene = random_scene(n=200, sh_degree=0, seed=3)
    cam = hp.Camera(48, 40, 40.0, 40.0, 24.0, 20.0)
    T = hp.Pose.identity()
    r = get_renderer(scene, hp.RasterConfig(tile_test="box"))
    r.render_full(cam, [T])
    ws = r.workspace(cam, 1)
    starts = read_rows(ws.tile_start, 1)[0]  # torch tensors with the parallel sort (CUDA)
    isect = read_rows(r.pool.lists.isect, int(starts[-1]))
    ref = bin_tiles(project(scene, cam, T.matrix()), cam)
    assert len(starts) == len(ref) + 1
    for t, ids in enumerate(ref):
        got = r.source_index[isect[starts[t]:starts[t + 1]]]  # resident (Morton) order -> scene indices
        np.testing.assert_array_equal(got, ids.numpy(), err_msg=f"tile {t}")


@pytest.mark.parametrize("size", [(64, 48), (200, 150)])  # 60 tiles in all; 650: more than one CPU task's 512
def test_batch_equals_one_by_one(size):
    scene = random_scene(n=300, sh_degree=1, seed=7)
    w, h = size
    cam = hp.Camera(w, h, 50.0 * w / 64, 50.0 * w / 64, w / 2, h / 2)
    poses = [hp.Pose.identity().perturbed_in_camera([0.01 * k, 0, -0.02 * k], [0, 0.03 * k, 0]) for k in range(5)]
    batch = hp.render(scene, cam, poses)
    assert batch.shape == (5, h, w, 3)
    for k, T in enumerate(poses):
        np.testing.assert_array_equal(batch[k], hp.render(scene, cam, T))


def test_chunked_batch_equals_unchunked():
    scene = random_scene(n=300, sh_degree=0, seed=8)
    cam = hp.Camera(40, 30, 35.0, 35.0, 20.0, 15.0)
    poses = [hp.Pose.identity().perturbed_in_camera([0, 0.02 * k, 0], [0, 0, 0]) for k in range(5)]
    full = hp.render(scene, cam, poses)
    chunked = hp.render(scene, cam, poses, config=RasterConfig(max_batch_elements=2 * 300))
    np.testing.assert_array_equal(full, chunked)


@pytest.mark.parametrize("metric", ["sad", "ssd"])
@pytest.mark.parametrize("mask_alpha", [0.0, 0.5])
def test_fused_cost_equals_image_cost(metric, mask_alpha):
    scene = random_scene(n=400, sh_degree=1, seed=11)
    cam = hp.Camera(72, 50, 60.0, 60.0, 36.0, 25.0)
    target = np.random.default_rng(0).uniform(size=(50, 72, 3)).astype(np.float32)
    poses = [hp.Pose.identity().perturbed_in_camera([0, 0.01 * k, 0], [0.01 * k, 0, 0]) for k in range(4)]
    bg = (0.1, 0.2, 0.3)
    costs = hp.render_cost(scene, cam, poses, target, metric=metric, background=bg, mask_alpha=mask_alpha)
    rgb, alpha, _ = hp.render_full(scene, cam, poses, background=bg)
    for k in range(4):
        valid = (alpha[k] >= mask_alpha)[..., None]
        d = (rgb[k].astype(np.float64) - target) * valid
        expect = np.abs(d).sum() if metric == "sad" else (d * d).sum()
        assert costs[k] == pytest.approx(expect, rel=2e-6), f"pose {k}"
    assert len(set(np.round(costs, 6))) > 1, "different poses must give different costs"


def test_depth_output_is_expected_depth():
    from hgsloc_plugin import GaussianScene

    # one opaque, large Gaussian at z = 2 straight ahead
    scene = GaussianScene.from_arrays([[0, 0, 2.0]], [[1, 0, 0, 0]], [[0.5, 0.5, 0.01]], [0.99],
                                      colors=[[1.0, 0.5, 0.0]])
    cam = hp.Camera(32, 32, 30.0, 30.0, 16.0, 16.0)
    rgb, alpha, depth = hp.render_full(scene, cam, hp.Pose.identity())
    assert alpha[16, 16] > 0.9
    assert depth[16, 16] == pytest.approx(2.0, abs=1e-4)
    np.testing.assert_allclose(rgb[16, 16] / alpha[16, 16], [1.0, 0.5, 0.0], atol=1e-3)


def test_nothing_visible_gives_background():
    scene = random_scene(n=50, seed=1)
    cam = hp.Camera(32, 24, 30.0, 30.0, 16.0, 12.0)
    behind = hp.Pose.look_at([0, 0, 0], [0, 0, -1], up=(0, 1, 0))
    rgb = hp.render(scene, cam, behind, background=(0.25, 0.5, 0.75))
    np.testing.assert_allclose(rgb, np.broadcast_to([0.25, 0.5, 0.75], rgb.shape), atol=1e-6)


def test_bad_arguments_raise():
    scene = random_scene(n=10)
    cam = hp.Camera(16, 16, 10.0, 10.0, 8.0, 8.0)
    with pytest.raises(TypeError):
        hp.render(scene, cam, np.eye(4))
    with pytest.raises(ValueError):
        hp.render(scene, cam, [])
    with pytest.raises(ValueError):
        hp.render_cost(scene, cam, hp.Pose.identity(), np.zeros((8, 8, 3)))
    with pytest.raises(ValueError):
        hp.render_cost(scene, cam, hp.Pose.identity(), np.zeros((16, 16, 3)), metric="nope")


@pytest.mark.parametrize("luminance", [False, True])
@pytest.mark.parametrize("mask_alpha", [0.0, 0.5])
@pytest.mark.parametrize("blend", ["splat", "pixel"])
def test_window_cost_kernel_matches_reference(luminance, mask_alpha, blend):
    """The fused windowed SSIM / cs kernel equals the float64 2D-convolution reference on each pose, with either
    image blend (the CPU's tile-parallel one, the GPU's per pixel)."""
    from hgsloc_plugin.render import get_renderer

    scene = random_scene(n=400, sh_degree=1, seed=11)
    cam = hp.Camera(72, 50, 60.0, 60.0, 36.0, 25.0)
    poses = [hp.Pose.identity().perturbed_in_camera([0, 0.01 * k, 0], [0.01 * k, 0, 0]) for k in range(4)]
    bg = (0.1, 0.2, 0.3)
    rgb, alpha, _ = hp.render_full(scene, cam, poses, background=bg)
    noise = np.random.default_rng(0).normal(0, 0.02, rgb[0].shape)
    query = np.clip(rgb[0] * 0.8 + 0.1 + noise, 0, 1).astype(np.float32)  # a gain/offset change and noise
    r = get_renderer(scene, RasterConfig(blend=blend))
    got = r.window_cost(cam, poses, r.upload_window_query(query), bg, mask_alpha, luminance)
    for k in range(4):
        s, n = window_cost(rgb[k], alpha[k], query, mask_alpha, luminance)
        assert got[k, 1] == n, f"pose {k}: valid pixels"
        assert got[k, 0] == pytest.approx(s, rel=1e-5, abs=1e-3), f"pose {k}"  # float32 passes vs float64
    assert len(set(np.round(got[:, 0], 3))) == 4, "different poses must give different sums"


def test_window_reference_agrees_with_kornia_ssim_inside_the_border():
    """The reference's SSIM equals kornia's away from the image border (they pad differently)."""
    kornia = pytest.importorskip("kornia")  # a dependency; a device image without it skips this check
    import torch

    rng = np.random.default_rng(3)
    a = rng.uniform(size=(40, 50, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1).astype(np.float32)
    ta, tb = (torch.from_numpy(x).permute(2, 0, 1)[None] for x in (a, b))
    kmap = kornia.metrics.ssim(ta, tb, window_size=11).mean(1)[0].double()  # [H, W]
    inner = np.zeros((40, 50), np.float32)
    inner[5:-5, 5:-5] = 1.0
    s, n = window_cost(a, inner, b, mask_alpha=0.5, luminance=True)
    assert n == 30 * 40
    assert s / n == pytest.approx(float(kmap[5:-5, 5:-5].mean()), abs=1e-5)


@pytest.mark.parametrize("dtype,shape", [("f32", (14, 6, 5, 3)), ("f32", (14, 6, 5)), ("f64", (14, 2)),
                                         ("i64", (14,)), ("i32", (3, 7))])
def test_read_rows_copies_only_the_rows_asked_for(dtype, shape):
    """``render.read_rows`` (``kernels/readback.py``) returns a workspace buffer's first n rows, equal to
    ``to_numpy()[:n]`` for every dtype and rank the renderer reads back."""
    import taichi as ti

    from hgsloc_plugin.render import read_rows

    hp.init()
    ti_dtype = {"f32": ti.f32, "f64": ti.f64, "i64": ti.i64, "i32": ti.i32}[dtype]
    values = (np.arange(int(np.prod(shape))).reshape(shape) * 3 - 7).astype({"f32": np.float32, "f64": np.float64,
                                                                              "i64": np.int64, "i32": np.int32}[dtype])
    arr = ti.ndarray(ti_dtype, shape)
    arr.from_numpy(values)
    for n in (1, 2, shape[0]):
        got = read_rows(arr, n)
        assert got.shape == (n,) + shape[1:] and got.dtype == values.dtype
        np.testing.assert_array_equal(got, values[:n])
