"""PLY reading/writing, malformed files, pose conversions (against pycolmap), cameras."""

from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest

from hgsloc_plugin import Camera, GaussianScene, Pose
from hgsloc_plugin.core.camera import Distortion, pose_cameras
from hgsloc_plugin.core.pose import rotation_angle_deg, so3_exp

from .conftest import random_scene


def test_round_trip_is_byte_exact(tmp_path):
    scene = random_scene(n=50, sh_degree=3, seed=2)
    a = scene.to_ply(tmp_path / "a.ply")
    back = GaussianScene.from_ply(a)
    b = back.to_ply(tmp_path / "b.ply")
    assert a.read_bytes() == b.read_bytes()
    np.testing.assert_allclose(back.means, scene.means)
    np.testing.assert_allclose(back.sh, scene.sh)
    np.testing.assert_allclose(back.opacities, scene.opacities, rtol=1e-5)
    np.testing.assert_allclose(back.scales, scene.scales, rtol=1e-5)


def test_real_files_round_trip_and_layout(tmp_path, donut, small_sh3):
    from .conftest import shared_path

    for scene, name in ((donut, "donut.ply"), (small_sh3, "small_sh3.ply")):
        out = scene.to_ply(tmp_path / name)
        assert out.read_bytes() == shared_path("scenes", name).read_bytes()
    assert donut.num_gaussians == 45624 and donut.sh_degree == 0
    assert small_sh3.num_gaussians == 9080 and small_sh3.sh_degree == 3
    np.testing.assert_allclose(np.linalg.norm(donut.quats, axis=1), 1.0, atol=1e-6)


def test_f_rest_is_channel_major_like_plyfile(small_sh3):
    from plyfile import PlyData

    from .conftest import shared_path

    v = PlyData.read(str(shared_path("scenes", "small_sh3.ply")))["vertex"]
    # coefficient k (1..15) of channel c is f_rest_{c*15 + k-1}
    for c in range(3):
        for k in (1, 7, 15):
            np.testing.assert_array_equal(small_sh3.sh[:, k, c], v[f"f_rest_{c * 15 + k - 1}"])
    np.testing.assert_allclose(small_sh3.opacities, 1 / (1 + np.exp(-v["opacity"].astype(np.float64))), rtol=1e-6)
    np.testing.assert_allclose(small_sh3.scales[:, 2], np.exp(v["scale_2"].astype(np.float64)), rtol=1e-6)


def _write(tmp_path, header_lines, body: bytes, name="bad.ply"):
    p = tmp_path / name
    p.write_bytes(("\n".join(header_lines) + "\n").encode() + body)
    return p


BASE_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
              "rot_0", "rot_1", "rot_2", "rot_3"]


def _header(props, n=2, fmt="binary_little_endian"):
    return ["ply", f"format {fmt} 1.0", f"element vertex {n}"] + [f"property float {p}" for p in props] + [
        "end_header"]


def _body(n, props, fill=None):
    a = np.ones((n, len(props)), "<f4")
    if fill:
        for k, v in fill.items():
            a[:, props.index(k)] = v
    return a.tobytes()


@pytest.mark.parametrize("case,match", [
    ("ascii", "binary_little_endian"),
    ("truncated", "truncated"),
    ("missing", "missing properties"),
    ("nan", "non-finite"),
    ("inf", "non-finite"),
    ("zero_quat", "zero rotation quaternion"),
    ("bad_rest", "f_rest"),
    ("not_ply", "not a PLY"),
])
def test_malformed_ply_names_file_and_problem(tmp_path, case, match):
    props = list(BASE_PROPS)
    if case == "ascii":
        p = _write(tmp_path, _header(props, 1, "ascii"), b" ".join([b"1"] * len(props)))
    elif case == "truncated":
        p = _write(tmp_path, _header(props, 3), _body(2, props))
    elif case == "missing":
        pr = [x for x in props if x != "scale_1"]
        p = _write(tmp_path, _header(pr), _body(2, pr))
    elif case in ("nan", "inf"):
        p = _write(tmp_path, _header(props), _body(2, props, {"y": np.nan if case == "nan" else np.inf}))
    elif case == "zero_quat":
        p = _write(tmp_path, _header(props), _body(2, props, {f"rot_{i}": 0.0 for i in range(4)}))
    elif case == "bad_rest":
        pr = props[:6] + [f"f_rest_{i}" for i in range(7)] + props[6:]
        p = _write(tmp_path, _header(pr), _body(2, pr))
    else:
        p = tmp_path / "bad.ply"
        p.write_bytes(b"hello world")
    with pytest.raises(ValueError, match=match) as ei:
        GaussianScene.from_ply(p)
    assert "bad.ply" in str(ei.value)


def test_from_arrays_validates():
    with pytest.raises(ValueError, match="means"):
        GaussianScene.from_arrays(np.zeros((3, 2)), np.ones((3, 4)), np.ones((3, 3)), np.full(3, 0.5),
                                  colors=np.zeros((3, 3)))
    with pytest.raises(ValueError, match="opacities"):
        GaussianScene.from_arrays(np.zeros((3, 3)), np.ones((3, 4)), np.ones((3, 3)), np.full(3, 1.5),
                                  colors=np.zeros((3, 3)))


def test_pose_conversions_against_pycolmap():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        t = rng.normal(size=3)
        T = Pose(q, t)
        rig = pycolmap.Rigid3d(pycolmap.Rotation3d(T.qvec[[1, 2, 3, 0]]), t)
        np.testing.assert_allclose(T.R, rig.rotation.matrix(), atol=1e-12)
        np.testing.assert_allclose(T.matrix34(), rig.matrix(), atol=1e-12)
        np.testing.assert_allclose(T.centre(), rig.inverse().translation, atol=1e-12)
        back = Pose.from_pycolmap(T.to_pycolmap())
        np.testing.assert_allclose(back.qvec, T.qvec, atol=1e-12)
        np.testing.assert_allclose(Pose.from_matrix(T.matrix()).qvec, T.qvec, atol=1e-12)
        np.testing.assert_allclose((T @ T.inv()).matrix(), np.eye(4), atol=1e-12)
        inv = rig.inverse()
        np.testing.assert_allclose(T.inv().matrix34(), inv.matrix(), atol=1e-12)


def test_pycolmap_quat_order_anchor():
    # CONVENTIONS §1: a 90 degree rotation about x is [0.7071, 0, 0, 0.7071] (x y z w) in pycolmap
    T = Pose([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0], [0, 0, 0])
    np.testing.assert_allclose(np.asarray(T.to_pycolmap().rotation.quat), [0.70710678, 0, 0, 0.70710678], atol=1e-7)


@pytest.mark.parametrize("q", [[0, 0, 0, 0], [np.nan, 1, 0, 0], [1, 0, np.inf, 0]])
def test_pose_rejects_bad_quaternions(q):
    with pytest.raises(ValueError):
        Pose(q, [0, 0, 0])


def test_pose_normalises_and_canonicalises_sign():
    T = Pose([-2, 0, 0, 0], [1, 2, 3])
    np.testing.assert_array_equal(T.qvec, [1, 0, 0, 0])


def test_pose_rotation_is_computed_once_and_handed_out_as_a_copy():
    """``Pose.R`` comes from the pose's own rotation, computed from the quaternion once: changing the array handed
    out changes neither the pose nor what it computes; a pickled pose (Ray sends them) equals the original."""
    import pickle

    from hgsloc_plugin.core.pose import qvec_to_rotmat

    p = Pose([0.9, 0.1, -0.3, 0.2], [0.5, -1.0, 2.0])
    R = p.R
    assert np.array_equal(R, qvec_to_rotmat(p.qvec))
    centre = p.centre()
    R[:] = 0.0
    assert np.array_equal(p.R, qvec_to_rotmat(p.qvec)) and np.array_equal(p.centre(), centre)
    q = pickle.loads(pickle.dumps(p))
    assert q == p and np.array_equal(q.R, p.R) and np.array_equal((q @ p.inv()).as_array(), (p @ p.inv()).as_array())


def test_one_quaternion_rotates_as_the_batch():
    from hgsloc_plugin.core.pose import qvec_to_rotmat, qvecs_to_rotmats

    q = np.random.default_rng(3).normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    batch = qvecs_to_rotmats(q)
    assert all(np.array_equal(qvec_to_rotmat(qi), Ri) for qi, Ri in zip(q, batch))  # bit for bit
    np.testing.assert_allclose(batch @ batch.transpose(0, 2, 1), np.broadcast_to(np.eye(3), batch.shape), atol=1e-12)


def test_rotation_angle_small_and_exact():
    for deg in (1e-4, 0.01, 1.0, 90.0, 179.0):
        R = so3_exp(np.array([0.3, -0.4, 0.5]) / np.linalg.norm([0.3, -0.4, 0.5]) * math.radians(deg))
        assert rotation_angle_deg(np.eye(3), R) == pytest.approx(deg, rel=1e-9)


def test_offset_in_camera_inverts_perturbed_in_camera():
    rng = np.random.default_rng(4)
    for k in range(20):
        base = Pose.identity().perturbed_in_camera(rng.normal(size=3), rng.normal(size=3) * 3)
        # rotations up to near pi (the log's hard end) and translations of any size
        w = rng.normal(size=3)
        w *= (0.05 + 3.0 * k / 20) / np.linalg.norm(w)
        v = rng.normal(size=3) * 2
        xi = base.offset_in_camera(base.perturbed_in_camera(w, v))
        np.testing.assert_allclose(xi, np.concatenate([w, v]), atol=1e-9)
        other = Pose.identity().perturbed_in_camera(rng.normal(size=3), rng.normal(size=3))
        back = base.perturbed_in_camera(*np.split(base.offset_in_camera(other), 2))
        np.testing.assert_allclose(back.matrix(), other.matrix(), atol=1e-9)


def test_camera_scaling_and_colmap_models():
    cam = Camera(640, 480, 525.0, 526.0, 320.0, 240.0)
    s = cam.scaled(0.25)
    assert (s.width, s.height, s.fx, s.cx) == (160, 120, 131.25, 80.0)
    assert cam.with_max_side(160) == s
    pc = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0])
    assert Camera.from_pycolmap(pc) == Camera(640, 480, 500.0, 500.0, 320.0, 240.0)
    # a model with distortion is carried (the refiner undistorts the photo), zero coefficients are a pinhole camera,
    # allow_distortion (photos already undistorted) drops them
    lens = Camera.from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, 0.01])
    assert lens.distortion == Distortion("SIMPLE_RADIAL", (0.01,)) and lens.pinhole == Camera(640, 480, 500.0, 500.0,
                                                                                              320.0, 240.0)
    assert lens.colmap_params() == ("SIMPLE_RADIAL", [500.0, 320.0, 240.0, 0.01])
    assert lens.scaled(0.5).distortion == lens.distortion
    assert Camera.from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, 0.0]).distortion is None
    assert Camera.from_colmap("OPENCV", 640, 480, [500, 501, 320, 240, 0, 0, 0, 0]) == Camera(640, 480, 500, 501, 320,
                                                                                             240)
    plain = Camera.from_colmap("SIMPLE_RADIAL", 640, 480, [500.0, 320.0, 240.0, 0.01], allow_distortion=True)
    assert plain.fx == 500 and plain.distortion is None
    with pytest.raises(ValueError, match="lens distortion"):  # a rendering is a pinhole image
        pose_cameras(lens, 1)
    # a parameter short or over is named with the model's parameter list (it was an IndexError or went unseen)
    with pytest.raises(ValueError, match=r"SIMPLE_PINHOLE takes 3 parameters \(f cx cy\), got 2"):
        Camera.from_colmap("SIMPLE_PINHOLE", 640, 480, [500.0, 320.0])
    with pytest.raises(ValueError, match=r"PINHOLE takes 4 parameters \(fx fy cx cy\), got 5"):
        Camera.from_colmap("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0, 0.1])
    with pytest.raises(ValueError):
        Camera(0, 10, 1.0, 1.0, 0.0, 0.0)


@pytest.mark.parametrize("src,dst", [((756, 1008), (240, 320)), ((240, 320), (75, 100)), ((240, 320), (150, 200)),
                                     ((148, 198), (74, 99)), ((37, 53), (80, 111)), ((480, 640), (479, 641))])
def test_resize_matches_torch_antialiased_bilinear(src, dst):
    """The query pyramid's resize against torch's ``interpolate(bilinear, antialias=True)`` (the reference)."""
    import torch
    import torch.nn.functional as F

    from hgsloc_plugin.core.image import resize_image

    img = np.random.default_rng(sum(src)).random(src + (3,)).astype(np.float32)
    out = resize_image(img, dst[1], dst[0])
    t = F.interpolate(torch.from_numpy(img).permute(2, 0, 1)[None], size=dst, mode="bilinear", antialias=True,
                      align_corners=False)
    ref = t[0].permute(1, 2, 0).numpy().clip(0, 1)
    assert out.shape == dst + (3,) and out.dtype == np.float32
    assert np.abs(out - ref).max() < 1e-4
    assert np.array_equal(out, resize_image(img, dst[1], dst[0]))  # deterministic


def test_package_and_query_loading_do_not_import_torch(tmp_path):
    """``import hgsloc_plugin``, loading and resizing a query leave torch unimported (2.5 s per process)."""
    import subprocess
    import sys

    from PIL import Image

    Image.fromarray(np.zeros((30, 40, 3), np.uint8)).save(tmp_path / "q.png")
    code = ("import sys, hgsloc_plugin as hp\n"
            "from hgsloc_plugin.core.image import load_image, resize_image\n"
            f"a = resize_image(load_image({str(tmp_path / 'q.png')!r}), 20, 15)\n"
            "print(a.shape, 'torch' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split() == ["(15,", "20,", "3)", "False"]


def test_query_arrays_in_every_layout_a_file_has(tmp_path):
    """Grey and RGBA arrays and tensors load as the same image as the file of that mode (grey repeated, RGBA
    composited on the map's background), uint8 and float alike; other layouts are refused naming the shape."""
    import torch
    from PIL import Image

    from hgsloc_plugin.core.image import load_image

    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, size=(6, 5, 4), dtype=np.uint8)
    bg = (0.25, 0.5, 1.0)
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    Image.fromarray(rgba[..., 0], "L").save(tmp_path / "g.png")
    from_file = load_image(tmp_path / "a.png", background=bg)
    grey_file = load_image(tmp_path / "g.png")
    alpha = rgba[..., 3:4] / 255.0
    expect = rgba[..., :3] / 255.0 * alpha + (1 - alpha) * np.array(bg)
    np.testing.assert_allclose(from_file, expect, atol=1e-6)
    for arr in (rgba, rgba / 255.0, torch.from_numpy(rgba).permute(2, 0, 1),
                torch.from_numpy(rgba / 255.0).permute(2, 0, 1)):
        np.testing.assert_allclose(load_image(arr, background=bg), from_file, atol=1e-6)
    g = rgba[..., 0]
    for arr in (g, g[..., None], g / 255.0, torch.from_numpy(g), torch.from_numpy(g)[None]):
        out = load_image(arr)
        assert out.shape == (6, 5, 3) and out.dtype == np.float32
        np.testing.assert_allclose(out, grey_file, atol=1e-6)
    half = load_image(torch.from_numpy(rgba / 255.0).permute(2, 0, 1).to(torch.bfloat16), background=bg)
    np.testing.assert_allclose(half, from_file, atol=1e-2)  # any float tensor, numpy has no bfloat16
    for bad in (np.zeros((6, 5, 2)), np.zeros((2, 6, 5, 3)), torch.zeros(2, 6, 5)):
        with pytest.raises(ValueError, match=r"must be \[.*got .*\(.*\)"):
            load_image(bad, name="q")
