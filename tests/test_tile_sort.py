"""The parallel tile sort (the GPU layout: a key per Gaussian and tile, a stable radix sort in Taichi;
RasterConfig.sort) against the serial one (the CPU layout), numpy's stable sort and the reference binning, all
run here on the CPU backend."""

from __future__ import annotations

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.cli.demo.queries import degrade
from hgsloc_plugin.render import get_renderer, read_rows

from .conftest import random_scene, room_query
from .reference.render_torch import bin_tiles, project
from .test_pose_grad import cost_case, moved


def renderers(scene, **kw):
    return [get_renderer(scene, hp.RasterConfig(sort=s, **kw)) for s in ("serial", "parallel")]


def lists(r, cam, n_poses, grad=False):
    """(tile_start [B, T + 1], the B poses' entries of isect) of a renderer's last binning at ``cam``."""
    ws = r.workspace(cam, n_poses, grad=grad)
    starts = read_rows(ws.tile_start, n_poses)
    return starts, read_rows(r.pool.lists.isect, int(starts[:, -1].sum()))


def test_parallel_lists_match_reference_binning():
    scene = random_scene(n=200, sh_degree=0, seed=3)
    cam = hp.Camera(48, 40, 40.0, 40.0, 24.0, 20.0)
    T = hp.Pose.identity()
    _, r = renderers(scene, tile_test="box")  # the reference bins by box (CUDA's default is the ellipse)
    assert r.sort_mode == "parallel"
    r.render_full(cam, [T])
    starts, isect = lists(r, cam, 1)
    ref = bin_tiles(project(scene, cam, T.matrix()), cam)
    assert starts.shape == (1, len(ref) + 1) and sum(len(ids) for ids in ref) > 100
    for t, ids in enumerate(ref):
        np.testing.assert_array_equal(r.source_index[isect[starts[0, t]:starts[0, t + 1]]], ids.numpy(),
                                      err_msg=f"tile {t}")


@pytest.mark.parametrize("case", ["random", "donut.ply", "small_sh3.ply", "room"])
def test_parallel_sort_equals_serial_entry_for_entry(case):
    """Tile lists, images, fused costs, windowed costs and visibility equal for batches of 1, 5 and 14 poses
    (several poses in one key sort: the pose index is the keys' top part), including exact depth ties (the
    random scene's duplicated Gaussians: ties stay in index order, as the serial radix sort leaves them)."""
    if case == "random":
        s = random_scene(n=400, sh_degree=1, seed=21)
        dup = np.arange(0, 400, 7)  # exact copies: equal depths, so the order of ties matters
        scene = hp.GaussianScene.from_arrays(np.concatenate([s.means, s.means[dup]]),
                                             np.concatenate([s.quats, s.quats[dup]]),
                                             np.concatenate([s.scales, s.scales[dup]]),
                                             np.concatenate([s.opacities, s.opacities[dup] * 0.5]),
                                             sh=np.concatenate([s.sh, s.sh[dup] * 0.7]))
        cam = hp.Camera(90, 70, 70.0, 70.0, 45.0, 33.0)
        T = hp.Pose.identity()
    else:
        scene, cam, T = cost_case(case)
    serial, parallel = renderers(scene)
    img = degrade(hp.render(scene, cam, moved(T, 3, 0.02)), np.random.default_rng(0))
    for count in (1, 5, 14):
        poses = [moved(T, k % 6, 0.003 * (k + 1) * (-1) ** k) for k in range(count)]
        outs = [r.render_full(cam, poses) for r in (serial, parallel)]
        for a, b in zip(*outs):
            np.testing.assert_array_equal(a, b)
        (sa, ia), (sb, ib) = (lists(r, cam, count) for r in (serial, parallel))
        assert sa[:, -1].sum() > 0
        np.testing.assert_array_equal(sa, sb)
        np.testing.assert_array_equal(ia, ib)
        target = [r.upload_image(img) for r in (serial, parallel)]
        np.testing.assert_array_equal(*(r.cost_stats(cam, poses, t) for r, t in zip((serial, parallel), target)))
        q = [r.upload_window_query(img) for r in (serial, parallel)]
        np.testing.assert_array_equal(*(r.window_cost(cam, poses, qq) for r, qq in zip((serial, parallel), q)))
        np.testing.assert_array_equal(*(r.visible(cam, poses) for r in (serial, parallel)))


@pytest.mark.parametrize("case", ["room", "small_sh3.ply"])
def test_parallel_sort_gives_the_same_derivatives_and_refinement(case):
    """The derivative pass (its own 8 px binning), the cs gradient and JtJ, and a whole refinement (search,
    polish, acceptance) give the same numbers and pose with either sort."""
    scene, cam, T = cost_case(case)
    serial, parallel = renderers(scene)
    img = degrade(hp.render(scene, cam, moved(T, 4, 0.01)), np.random.default_rng(0))
    poses = [T, moved(T, 1, 0.004), moved(T, 5, -0.003)]
    for a, b in zip(serial.render_derivatives(cam, poses), parallel.render_derivatives(cam, poses)):
        np.testing.assert_array_equal(a, b)
    (sa, ia), (sb, ib) = (lists(r, cam, 3, grad=True) for r in (serial, parallel))
    np.testing.assert_array_equal(sa, sb)
    np.testing.assert_array_equal(ia, ib)
    q = [r.upload_window_query(img) for r in (serial, parallel)]
    for a, b in zip(serial.pose_gradient(cam, poses, q[0]), parallel.pose_gradient(cam, poses, q[1])):
        np.testing.assert_array_equal(a, b)


def test_parallel_sort_refines_to_the_same_pose():
    cam = hp.Camera.from_fov(160, 120, 65.0)
    scene, gt, img, prior = room_query(cam, pose_seed=4, noise_deg=1.0, noise_shift=0.03, noise_seed=2)
    img = degrade(img, np.random.default_rng(1))
    # working sets: pooled buffers wider than the Gaussians sorted
    cfg = hp.RefineConfig.preset("default", working_set_min=0)
    res = [hp.HGSLocPlugin(scene, cfg, raster=hp.RasterConfig(sort=s)).refine(img, cam, prior)
           for s in ("serial", "parallel")]
    assert res[0].renders == res[1].renders and res[0].renders > 12  # a whole refinement: line searches, the rule
    np.testing.assert_array_equal(res[0].pose.qvec, res[1].pose.qvec)
    np.testing.assert_array_equal(res[0].pose.tvec, res[1].pose.tvec)
    assert res[0].pose.errors_to(gt)[0] < prior.errors_to(gt)[0]


def test_sort_setting_is_checked():
    with pytest.raises(ValueError, match="sort must be"):
        hp.RasterConfig(sort="gpu")


def test_sort_mode_per_backend():
    """auto: serial on the CPU, parallel on CUDA (every step a Taichi kernel: no CUDA torch needed)."""
    from hgsloc_plugin.render.buffers import sort_mode

    assert sort_mode("auto", "cpu") == "serial" and sort_mode("auto", "cuda") == "parallel"
    assert sort_mode("parallel", "cpu") == "parallel" and sort_mode("serial", "cuda") == "serial"


def test_no_torch_in_the_render_path():
    """The renderer and its kernels import no torch (a CPU-only torch beside CUDA Taichi runs the fast path)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for f in [*(root / "kernels").glob("*.py"), *(root / "hgsloc_plugin" / "render").glob("*.py")]:
        for node in ast.walk(ast.parse(f.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            assert not any(n.split(".")[0] == "torch" for n in names), f"{f.name} imports torch"


@pytest.mark.parametrize("m,bits,dupes", [(1, 40, False), (700, 40, True), (50_000, 48, True), (0, 40, False)])
def test_radix_sort_is_a_stable_sort(m, bits, dupes):
    """``kernels/radix.py`` against numpy's stable sort: random 48-bit keys (many equal with ``dupes``), ids in
    input order; blocks of several sizes (one block, many, a partial last one)."""
    import taichi as ti

    from hgsloc_plugin.kernels import radix

    hp.init("cpu")
    rng = np.random.default_rng(m)
    keys = rng.integers(0, 1 << (bits - 1), size=max(m, 1), dtype=np.int64)
    if dupes:
        keys = keys[rng.integers(0, max(m // 10, 1), size=max(m, 1))]
    ids = np.arange(max(m, 1), dtype=np.int32)

    def nd(a):
        out = ti.ndarray(ti.i64 if a.dtype == np.int64 else ti.i32, a.shape)
        out.from_numpy(np.ascontiguousarray(a))
        return out

    k, i = nd(keys), nd(ids)
    kt, it = nd(np.zeros_like(keys)), nd(np.zeros_like(ids))
    counts = ti.ndarray(ti.i32, (radix.DIGITS, radix.MAX_BLOCKS))
    offsets = ti.ndarray(ti.i64, (radix.DIGITS * radix.MAX_BLOCKS + 1,))
    sums = ti.ndarray(ti.i64, (radix.MAX_BLOCKS + 1,))
    ks, is_ = radix.radix_sort(k, i, kt, it, m, bits, counts, offsets, sums)
    order = np.argsort(keys[:m], kind="stable")
    np.testing.assert_array_equal(ks.to_numpy()[:m], keys[:m][order])
    np.testing.assert_array_equal(is_.to_numpy()[:m], ids[:m][order])
    if m:  # the scan: exclusive prefix sums and the total
        vals = rng.integers(0, 9, size=(3, m), dtype=np.int32)
        out = ti.ndarray(ti.i64, (2 * m + 2,))
        radix.exclusive_scan(nd(vals), 2, m, sums, out)
        flat = vals[:2].reshape(-1).astype(np.int64)
        np.testing.assert_array_equal(out.to_numpy()[:2 * m + 1], np.concatenate([[0], np.cumsum(flat)]))


def test_parallel_sort_with_nothing_in_view():
    """A batch where one pose sees no Gaussian (zero keys for it, or for the whole call) renders the background,
    as the serial sort does."""
    scene = random_scene(n=150, sh_degree=0, seed=4)
    cam = hp.Camera(40, 30, 35.0, 35.0, 20.0, 15.0)
    away = hp.Pose.identity().perturbed_in_camera([0.0, np.pi, 0.0], [0.0, 0.0, 0.0])  # looking down -z
    serial, parallel = renderers(scene)
    for poses in ([away], [hp.Pose.identity(), away, hp.Pose.identity()]):
        a, b = (r.render_full(cam, poses, background=(0.1, 0.2, 0.3)) for r in (serial, parallel))
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_allclose(b[0][poses.index(away)], np.broadcast_to([0.1, 0.2, 0.3], (30, 40, 3)), atol=1e-7)
        starts, _ = lists(parallel, cam, len(poses))
        assert starts[poses.index(away), -1] == 0 and starts[:, -1].sum() == (0 if len(poses) == 1 else
                                                                            starts[0, -1] * 2)


@pytest.mark.parametrize("sort", ["serial", "parallel"])
def test_ellipse_footprint_drops_only_tiles_the_gaussian_cannot_reach(sort):
    """``tile_test="ellipse"`` against ``"box"``: each tile's list is the box binning's without the Gaussians
    whose alpha cannot reach ``alpha_min`` at any of the tile's pixel centres (float64 reference over every
    pixel of the tile, from the box renderer's records), in the same order; images, windowed costs and pose
    derivatives equal to float32 rounding. (Not bit for bit: the two projection kernels differ in the code after
    the records, and LLVM's fast math may round the records' shared terms differently, up to ~1e-4 of a pixel.)"""
    from hgsloc_plugin.kernels.layout import Rec

    scene, cam, T = cost_case("room")
    box, ell = (get_renderer(scene, hp.RasterConfig(sort=sort, tile_test=t)) for t in ("box", "ellipse"))
    poses = [T, moved(T, 1, 0.004), moved(T, 5, -0.02)]
    for a, b in zip(box.render_full(cam, poses), ell.render_full(cam, poses)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4)  # a reachable Gaussian dropped: alpha >= 1/255
    (sa, ia), (sb, ib) = (lists(r, cam, len(poses)) for r in (box, ell))
    packed = read_rows(box.pool.records.packed, len(poses)).astype(np.float64)
    tile, tx = box.config.tile_size, -(-cam.width // box.config.tile_size)
    kept = dropped = 0
    base_a = base_b = 0
    for p in range(len(poses)):
        for t in range(sa.shape[1] - 1):
            full = ia[base_a + sa[p, t]:base_a + sa[p, t + 1]]
            part = ib[base_b + sb[p, t]:base_b + sb[p, t + 1]]
            keep = np.isin(full, part)
            np.testing.assert_array_equal(full[keep], part, err_msg=f"pose {p} tile {t}")
            x0, y0 = (t % tx) * tile, (t // tx) * tile
            px, py = np.meshgrid(np.arange(x0, min(x0 + tile, cam.width)) + 0.5,
                                 np.arange(y0, min(y0 + tile, cam.height)) + 0.5)
            rec = packed[p, full[~keep]]
            dx = rec[:, Rec.X, None, None] - px
            dy = rec[:, Rec.Y, None, None] - py
            sigma = (0.5 * (rec[:, Rec.CA, None, None] * dx * dx + rec[:, Rec.CC, None, None] * dy * dy)
                     + rec[:, Rec.CB, None, None] * dx * dy)
            assert np.all(sigma.min(axis=(1, 2)) > rec[:, Rec.LIM]), f"pose {p} tile {t}: a reachable tile dropped"
            kept, dropped = kept + len(part), dropped + int((~keep).sum())
        base_a, base_b = base_a + sa[p, -1], base_b + sb[p, -1]
    assert dropped > 0.05 * (kept + dropped), (kept, dropped)
    img = degrade(hp.render(scene, cam, moved(T, 3, 0.02)), np.random.default_rng(0))
    q = [r.upload_window_query(img) for r in (box, ell)]
    np.testing.assert_allclose(box.window_cost(cam, poses, q[0]), ell.window_cost(cam, poses, q[1]), rtol=1e-4)
    for a, b in zip(box.pose_gradient(cam, poses, q[0]), ell.pose_gradient(cam, poses, q[1])):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-3 * np.abs(a).max())


def test_cuda_layout_is_what_auto_picks_on_cuda():
    """``kernels.config.CUDA_LAYOUT`` (CUDA's layout forced on any backend) names what each "auto" resolves to on
    CUDA, and resolves there as the default config does."""
    from hgsloc_plugin.kernels.config import CUDA_LAYOUT
    from hgsloc_plugin.kernels.footprint import uses_ellipse_tiles
    from hgsloc_plugin.kernels.pose_grad import uses_masks
    from hgsloc_plugin.render.buffers import blend_mode, sort_mode

    auto, forced = hp.RasterConfig(), hp.RasterConfig(**CUDA_LAYOUT)
    for config in (auto, forced):
        splat = blend_mode(config.blend, "cuda") == "splat"
        picks = {"blend": blend_mode(config.blend, "cuda"), "sort": sort_mode(config.sort, "cuda"),
                 "grad_masks": "on" if uses_masks(config, "cuda", splat) else "off",
                 "tile_test": "ellipse" if uses_ellipse_tiles(config, "cuda") else "box"}
        assert picks == CUDA_LAYOUT, config
    assert blend_mode("auto", "cpu") == "splat" and blend_mode("pixel", "cpu") == "pixel"


def test_tile_test_per_backend():
    """auto: the ellipse on CUDA, the box on the CPU; a bad setting is refused."""
    from hgsloc_plugin.kernels.footprint import uses_ellipse_tiles

    auto = hp.RasterConfig()
    assert uses_ellipse_tiles(auto, "cuda") and not uses_ellipse_tiles(auto, "cpu")
    assert uses_ellipse_tiles(hp.RasterConfig(tile_test="ellipse"), "cpu")
    with pytest.raises(ValueError, match="tile_test must be"):
        hp.RasterConfig(tile_test="exact")
