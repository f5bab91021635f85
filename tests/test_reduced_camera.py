"""Cameras of reduced images (``Camera.downsample``): the rendering against the independent reference
(tests/reference/render_torch.py), its match to a finer rendering reduced by ``resize_image``, and the derivative
pass, which holds the filter's opacity compensation fixed, against float64 finite differences."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import hgsloc_plugin as hp
from hgsloc_plugin.render import get_renderer

from .conftest import random_scene
from .reference.render_torch import project, render_reference
from .test_render import DONUT_VIEWS, assert_matches


@pytest.mark.parametrize("downsample", [1.6, 3.2])
def test_reduced_image_camera_matches_reference(donut, downsample):
    """A camera of a reduced image (``Camera.downsample``): the dilation scaled, the reduction's filter with its
    opacity compensation, as the reference computes them; and not the plain rendering."""
    scene = random_scene(n=300, sh_degree=1, seed=4)
    T = hp.Pose.identity().perturbed_in_camera([0.02, -0.03, 0.01], [0.05, 0.0, -0.1])
    for sc, cam, pose in ((scene, hp.Camera(70, 45, 60.0, 62.0, 33.0, 24.5), T),
                          (donut, hp.Camera.from_fov(64, 48, 50.0), hp.Pose.look_at(*DONUT_VIEWS[0]))):
        reduced = dataclasses.replace(cam, downsample=downsample)
        rgb, alpha, _ = hp.render_full(sc, reduced, pose)
        ref, ref_alpha = render_reference(sc, reduced, pose)
        assert_matches(rgb, ref, f"downsample {downsample}")
        assert np.abs(alpha - ref_alpha).max() < 1e-3
        plain = hp.render(sc, cam, pose)
        assert np.abs(rgb - plain).max() > 0.02, "the filter must change the rendering"


def test_reduced_image_camera_renders_the_finer_rendering_reduced():
    """Sub-pixel Gaussians (the demo room split 20 times) rendered at 100x75 with ``downsample`` 3.2 come out
    much closer to the 320x240 rendering reduced by ``resize_image`` than the plain 100x75 rendering does."""
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.run import QUERY_CAMERA
    from hgsloc_plugin.cli.demo.scene import densify_split, make_room_scene
    from hgsloc_plugin.core.image import resize_image

    scene = densify_split(make_room_scene(), 20)
    small = QUERY_CAMERA.resized(100, 75)
    for pose in query_poses(2, seed=1):
        target = resize_image(hp.render(scene, QUERY_CAMERA, pose), 100, 75)
        plain = np.abs(hp.render(scene, small, pose) - target).mean()
        reduced = dataclasses.replace(small, downsample=QUERY_CAMERA.width / 100)
        filtered = np.abs(hp.render(scene, reduced, pose) - target).mean()
        assert filtered < 0.5 * plain, (filtered, plain)


def _fd(scene, cam, T, k, h, factor):
    xi = np.zeros(6)
    out = []
    for s in (h, -h):
        xi[k] = s
        out.append(render_reference(scene, cam, T.perturbed_in_camera(xi[:3], xi[3:]), dtype=torch.float64,
                                    fixed_filter=factor)[0])
    return (out[0] - out[1]) / (2 * h)


@pytest.mark.parametrize("downsample", [2.0, 3.2])
def test_reduced_image_derivatives_hold_the_compensation_fixed(downsample):
    """The derivative images of a reduced camera equal the float64 reference's finite differences with each
    Gaussian's opacity compensation held at its value at the pose (1 % relative L2 on the smooth pixels, the
    tolerance of tests/test_pose_grad.py); against the full differences, the compensation's own change is what
    is left out: measured 2026-12-07 at 2.2-2.4 % (relative L2) of the translation along the view, under 0.3 %
    of the others (compensation factors 0.5-1, median 0.86)."""
    s = random_scene(n=300, sh_degree=0, seed=1)
    scene = hp.GaussianScene.from_arrays(s.means, s.quats, s.scales * 0.5, s.opacities * 0.5, sh=s.sh)
    cam = dataclasses.replace(hp.Camera.from_fov(64, 48, 50.0), downsample=downsample)
    T = hp.Pose.identity().perturbed_in_camera([0.02, -0.01, 0.03], [0.05, 0.02, -0.1])
    rgb, _, d = get_renderer(scene).render_derivatives(cam, [T])
    factor = project(scene, cam, T.matrix(), dtype=torch.float64)["factor"]
    assert float(factor.min()) < 0.7, "the filter must matter here"
    assert np.abs(rgb[0] - render_reference(scene, cam, T, dtype=torch.float64)[0]).max() < 1e-4
    for k in range(6):
        f1, f2, f3 = (_fd(scene, cam, T, k, h, factor) for h in (4e-7, 2e-7, 1e-7))
        scale = np.percentile(np.abs(f2), 99)
        smooth = (np.abs(f1 - f2) < 0.01 * scale) & (np.abs(f2 - f3) < 0.01 * scale)
        assert smooth.mean() >= 0.93, (k, smooth.mean())
        err = np.abs(d[0, ..., k] - f3)[smooth]
        assert np.linalg.norm(err) / np.linalg.norm(f3[smooth]) < 0.01, k
        full = _fd(scene, cam, T, k, 1e-7, None)
        rel = np.linalg.norm((d[0, ..., k] - full)[smooth]) / np.linalg.norm(full[smooth])
        assert rel < (0.03 if k == 5 else 0.01), (k, rel)


def test_working_set_of_reduced_cameras_renders_like_the_whole_map():
    """The working set's bound covers a reduced camera's wider footprint (a reduction of 1.25, where the
    widening 0.3 / 1.25^2 + 1/6 exceeds 3DGS's 0.3): images bit-identical to the whole map's on the region."""
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import densify, make_room_scene

    from .test_working_set import check_equal

    scene = densify(make_room_scene(), 2)
    cam = hp.Camera.from_fov(320, 240, 65.0)
    cams = [dataclasses.replace(cam.resized(256, 192), downsample=1.25),
            dataclasses.replace(cam.resized(100, 75), downsample=3.2)]
    frac = check_equal(scene, cams, query_poses(1, seed=1)[0], 0.10, 3.0)
    assert frac < 0.6, frac


@pytest.mark.parametrize("antialias", [True, False])
def test_plan_marks_each_scoring_size_below_the_image_as_its_reduction(antialias):
    from hgsloc_plugin.core.prior import QueryPrior
    from hgsloc_plugin.refine.plan import make_plan

    scene = random_scene(n=200, sh_degree=0, seed=2)
    camera = hp.Camera.from_fov(640, 480, 60.0)
    cfg = hp.RefineConfig.preset("default", antialias=antialias)
    plan = make_plan(cfg, scene, camera, hp.Pose.identity(), QueryPrior())
    for cam in (plan.cam_final, plan.cam_coarse, plan.cam_polish):
        assert cam.width < camera.width
        want = 0.5 * (camera.width / cam.width + camera.height / cam.height) if antialias else 1.0
        assert cam.downsample == pytest.approx(want), (cam.width, cam.downsample)
    assert plan.cam_wide.width < camera.width and plan.cam_wide.downsample == 1.0  # its lattice's renders stay plain
    same = make_plan(cfg, scene, camera.resized(320, 240), hp.Pose.identity(), QueryPrior())
    assert same.cam_polish.width == 320 and same.cam_polish.downsample == 1.0  # the image's size: 3DGS's rendering
