"""Photos through a lens with distortion: ``image.undistort`` (pycolmap's camera models) against kornia's lens
models as the independent reference, and a distorted real photo refined end to end with no flag."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

import hgsloc_plugin as hp
from hgsloc_plugin.core.image import undistort

from .conftest import shared_path

#: COLMAP model, its distortion coefficients (COLMAP order), and the kornia call distorting normalised points
LENSES = {
    "SIMPLE_RADIAL": ([0.12], lambda k: ("opencv", [k[0], 0.0, 0.0, 0.0])),
    "RADIAL": ([-0.2, 0.05], lambda k: ("opencv", [k[0], k[1], 0.0, 0.0])),
    "OPENCV": ([-0.25, 0.08, 0.002, -0.001], lambda k: ("opencv", k)),
    "FULL_OPENCV": ([-0.2, 0.05, 0.001, 0.002, -0.01, 0.01, 0.002, 0.0], lambda k: ("opencv", k)),
    "OPENCV_FISHEYE": ([0.05, -0.02, 0.004, -0.001], lambda k: ("fisheye", k)),
}


def kornia_distorted(xy: np.ndarray, kind: str, coeffs) -> np.ndarray:
    """Normalised pinhole coordinates [N, 2] -> normalised distorted coordinates [N, 2], by kornia's models."""
    from kornia.geometry.calibration import distort_points
    from kornia.geometry.camera import distort_points_kannala_brandt

    p = torch.from_numpy(xy.astype(np.float64))
    if kind == "fisheye":
        return distort_points_kannala_brandt(p, torch.tensor([1.0, 1.0, 0.0, 0.0, *coeffs], dtype=torch.float64)
                                             ).numpy()
    return distort_points(p[None], torch.eye(3, dtype=torch.float64)[None],
                          torch.tensor([coeffs], dtype=torch.float64))[0].numpy()


def pattern(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A smooth colour image as a function of pixel coordinates (centres at +0.5): [..., 3] in [0, 1]."""
    return np.stack([0.5 + 0.4 * np.sin(u / 9.0) * np.cos(v / 11.0), 0.5 + 0.4 * np.cos((u + v) / 13.0),
                     0.5 + 0.3 * np.sin(v / 7.0)], -1).astype(np.float32)


@pytest.mark.parametrize("model", sorted(LENSES))
def test_undistortion_samples_where_kornias_lens_model_maps_each_pixel(model):
    coeffs, how = LENSES[model]
    single = model in ("SIMPLE_RADIAL", "RADIAL")
    k = [150.0, 101.0, 76.0] if single else [150.0, 152.0, 101.0, 76.0]
    cam = hp.Camera.from_colmap(model, 200, 150, k + coeffs)
    v, u = np.mgrid[0:150, 0:200] + 0.5
    photo = pattern(u, v)  # the photo as the lens saw it
    img, pin = undistort(photo, cam)
    assert pin.distortion is None and (pin.fx, pin.fy) == (cam.fx, cam.fy)  # COLMAP keeps the focal lengths
    # where each pinhole pixel centre lies in the photo, by kornia's model
    pv, pu = np.mgrid[0:pin.height, 0:pin.width] + 0.5
    xy = np.stack([(pu - pin.cx) / pin.fx, (pv - pin.cy) / pin.fy], -1).reshape(-1, 2)
    kind, kc = how(coeffs)
    d = kornia_distorted(xy, kind, kc)
    du = (cam.fx * d[:, 0] + cam.cx).reshape(pin.height, pin.width)
    dv = (cam.fy * d[:, 1] + cam.cy).reshape(pin.height, pin.width)
    inside = (du > 1) & (du < 199) & (dv > 1) & (dv < 149)
    assert inside.mean() > 0.97  # COLMAP's undistorted camera leaves (almost) no pixel outside the photo
    expect = pattern(du, dv)
    err = np.abs(img - expect)[inside]
    assert err.max() < 0.01, (model, err.max())  # bilinear sampling of a smooth image, at the right places
    # a camera without distortion is left alone; one with is never rendered
    same, c = undistort(photo, cam.pinhole)
    assert same is photo and c == cam.pinhole


def test_a_pinhole_rendering_distorted_and_undistorted_comes_back():
    """Round trip through both directions on a rendering: kornia distorts, ``undistort`` undoes it."""
    import torch.nn.functional as F
    from kornia.geometry.calibration import undistort_points

    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene

    scene = make_room_scene(density=0.3)
    pin = hp.Camera.from_fov(200, 150, 60.0)
    gt = query_poses(1, seed=4)[0]
    lens = hp.Camera.from_colmap("OPENCV", 200, 150, [pin.fx * 1.15, pin.fy * 1.15, pin.cx, pin.cy,
                                                      -0.25, 0.08, 0.0, 0.0])
    sharp = hp.render(scene, pin, gt)
    # the lens's photo: each of its pixels looks where kornia's inverse model says, sampled from the rendering
    v, u = np.mgrid[0:150, 0:200] + 0.5
    xy = np.stack([(u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy], -1).reshape(1, -1, 2)
    und = undistort_points(torch.from_numpy(xy), torch.eye(3, dtype=torch.float64)[None],
                           torch.tensor([[-0.25, 0.08, 0.0, 0.0]], dtype=torch.float64), num_iters=20)[0].numpy()
    pu, pv = pin.fx * und[:, 0] + pin.cx, pin.fy * und[:, 1] + pin.cy
    grid = torch.from_numpy(np.stack([2 * pu / 200 - 1, 2 * pv / 150 - 1], -1).reshape(1, 150, 200, 2)).float()
    photo = F.grid_sample(torch.from_numpy(sharp).permute(2, 0, 1)[None], grid, align_corners=False,
                          padding_mode="border")[0].permute(1, 2, 0).numpy()
    img, cam = undistort(photo, lens)
    back = hp.render(scene, cam, gt)
    inner = np.s_[8:-8, 8:-8]
    psnr = -10 * np.log10(np.mean((img[inner] - back[inner]) ** 2))
    flat = -10 * np.log10(np.mean((photo[inner] - hp.render(scene, lens.pinhole, gt)[inner]) ** 2))
    assert psnr > 28 and psnr > flat + 8, (psnr, flat)  # the photo read as if pinhole matches far worse


@pytest.mark.slow
def test_a_distorted_real_photo_refines_with_no_flag(tmp_path):
    """Issue 64's goal: a snow photo distorted through OPENCV k1 = -0.25, k2 = 0.08 and its distorted query list
    refine, with no flag, to within 0.6 % of the depth from 1 % / 0.5 deg priors, as the photo itself does."""
    import torch.nn.functional as F
    from kornia.geometry.calibration import undistort_points
    from PIL import Image

    from hgsloc_plugin.adapters import read_poses
    from hgsloc_plugin.evaluation.noise import se3_noise
    from hgsloc_plugin.evaluation.viz import save_png
    from hgsloc_plugin.refine.plan import median_depth

    snow = shared_path("snow")
    cj = json.loads((snow / "camera.json").read_text())
    pin = hp.Camera(cj["width"], cj["height"], cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    scene = hp.GaussianScene.from_ply(snow / "snow_sharp.ply")
    gt = read_poses(snow / "gt.txt")
    names = list(gt)[1:3]  # (the first photo's map floor on this map is 1.1 % of the depth, benchmarks/map_floor.md)
    k = [pin.fx * 1.15, pin.fy * 1.15, pin.cx, pin.cy, -0.25, 0.08, 0.0, 0.0]  # a narrower lens: no blank corner
    lens = hp.Camera.from_colmap("OPENCV", pin.width, pin.height, k)
    (tmp_path / "plain").mkdir()
    (tmp_path / "lens").mkdir()
    v, u = np.mgrid[0:pin.height, 0:pin.width] + 0.5
    xy = np.stack([(u - lens.cx) / lens.fx, (v - lens.cy) / lens.fy], -1).reshape(1, -1, 2)
    und = undistort_points(torch.from_numpy(xy), torch.eye(3, dtype=torch.float64)[None],
                           torch.tensor([k[4:]], dtype=torch.float64), num_iters=20)[0].numpy()
    grid = np.stack([2 * (pin.fx * und[:, 0] + pin.cx) / pin.width - 1,
                     2 * (pin.fy * und[:, 1] + pin.cy) / pin.height - 1], -1).reshape(1, pin.height, pin.width, 2)
    rng = np.random.default_rng(5)
    lines = []
    for n in names:
        photo = np.asarray(Image.open(snow / "queries" / n).convert("RGB"), np.float32) / 255
        save_png(photo, tmp_path / "plain" / n)
        bent = F.grid_sample(torch.from_numpy(photo).permute(2, 0, 1)[None], torch.from_numpy(grid).float(),
                             align_corners=False, padding_mode="border")[0].permute(1, 2, 0).numpy()
        save_png(bent, tmp_path / "lens" / n)
        prior = se3_noise(gt[n], 0.5, 0.01 * median_depth(scene, pin, gt[n]), rng)
        lines.append(" ".join([n] + [repr(float(x)) for x in prior.as_array()]))
    (tmp_path / "prior.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "lens.txt").write_text("".join(f"{n} OPENCV {pin.width} {pin.height} {' '.join(map(str, k))}\n"
                                               for n in names))
    (tmp_path / "plain.txt").write_text("".join(f"{n} PINHOLE {pin.width} {pin.height} {pin.fx} {pin.fy} {pin.cx} "
                                                f"{pin.cy}\n" for n in names))
    errors = {}
    for kind in ("lens", "plain"):
        out = tmp_path / f"{kind}_refined.txt"
        p = subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli", "refine", "--scene", snow / "snow_sharp.ply",
                            "--poses", tmp_path / "prior.txt", "--images", tmp_path / kind, "--intrinsics",
                            tmp_path / f"{kind}.txt", "--out", out, "--quiet"], capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        assert ("undistorting the query photos (OPENCV" in p.stderr) == (kind == "lens")
        assert "--allow-distortion" in p.stderr or kind == "plain"
        est = read_poses(out)
        errors[kind] = [est[n].errors_to(gt[n])[0] / median_depth(scene, pin, gt[n]) for n in names]
    assert max(errors["lens"]) < 0.006 and max(errors["plain"]) < 0.006, errors
