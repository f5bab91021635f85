"""What a pipeline script relies on, run as a user runs it (subprocesses): file modes, exit codes, JSON on error,
strict pose files, units, perturbed priors, transforms.json."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys

import numpy as np
import pytest

from hgsloc_plugin.adapters import read_poses

from .conftest import shared_path
from .test_cli_demo import tiny_case  # noqa: F401  (module-scoped fixture shared with the CLI tests)


def hgsloc(*args, umask: int | None = None) -> subprocess.CompletedProcess:
    """``hgsloc ARGS`` in a fresh process (with ``umask`` set for it)."""
    pre = (lambda: os.umask(umask)) if umask is not None else None
    return subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli", *map(str, args)], capture_output=True,
                          text=True, preexec_fn=pre)


def refine_args(d, out, *extra, images=None):
    return ["refine", "--scene", d / "scene.ply", "--poses", d / "ace.txt", "--images", images or d / "images",
            "--focal", "90", "--out", out, "--config", "fast", "--quiet", "--skip-check", *extra]


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.slow
def test_outputs_follow_the_umask(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    for umask, want in ((0o022, 0o644), (0o077, 0o600), (0o002, 0o664)):
        out = tmp_path / f"r{umask:o}.txt"
        p = hgsloc(*refine_args(d, out, "--limit", "1", "--figures", tmp_path / f"fig{umask:o}"), umask=umask)
        assert p.returncode == 0, p.stderr
        figs = list((tmp_path / f"fig{umask:o}").glob("*.png"))
        assert figs, "a figure was written"
        for f in [out, tmp_path / f"r{umask:o}.txt.json", *figs]:
            assert mode(f) == want, (f, oct(mode(f)), oct(want))
    p = hgsloc("perturb", "--poses", d / "gt.txt", "--noise", "2cm,1deg", "--out", tmp_path / "n.txt", umask=0o022)
    assert p.returncode == 0 and mode(tmp_path / "n.txt") == 0o644


@pytest.mark.slow
def test_refine_exits_3_when_a_query_failed_and_writes_the_rest(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    imgs = tmp_path / "images"
    shutil.copytree(d / "images", imgs)
    (imgs / "seq-01" / "frame-000002.color.png").unlink()
    out = tmp_path / "o.txt"
    p = hgsloc(*refine_args(d, out, "--json", images=imgs))
    assert p.returncode == 3, p.stderr
    rep = json.loads(p.stdout)  # stdout is one JSON object
    assert list(rep["failed"]) == ["seq-01-frame-000002.color.png"] and rep["totals"]["queries"] == 3
    assert "failed: seq-01-frame-000002.color.png: FileNotFoundError" in p.stderr
    assert len(read_poses(out)) == 3
    # check samples every query here: an unreadable one fails it (exit 1) and is named
    c = hgsloc("check", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", imgs, "--focal", "90",
               "--json")
    assert c.returncode == 1, c.stderr
    rep = json.loads(c.stdout)
    assert list(rep["unreadable"]) == ["seq-01/frame-000002.color.png"] and "could not be read" in rep["message"]
    assert rep["verdict"] == "ok"  # the readable ones agree
    ok = hgsloc("check", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", d / "images", "--focal",
                "90")
    assert ok.returncode == 0, ok.stdout + ok.stderr


def test_a_junk_line_is_an_error_naming_file_and_line(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    lines = (d / "gt.txt").read_text().splitlines()
    bad = tmp_path / "results.txt"
    bad.write_text("\n".join(lines[:2] + ["lorem ipsum dolor"] + lines[2:]) + "\n")
    out = tmp_path / "o.txt"
    for extra in ([], ["--json"]):
        p = hgsloc(*refine_args(d, out, *extra)[:4], bad, *refine_args(d, out, *extra)[5:])
        assert p.returncode == 2 and not out.exists(), p.stderr
        assert f"{bad}:3: neither a pose record nor a printed tensor: 'lorem ipsum dolor'" in p.stderr
        assert p.stderr.count("lorem") == 1  # one message, no warning repeating it
        if extra:
            assert json.loads(p.stdout) == {"error": json.loads(p.stdout)["error"], "file": str(bad), "line": 3}


def test_every_json_command_answers_in_json_on_error(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    cases = [
        (["evaluate", "--poses", tmp_path / "none.txt", "--gt", d / "gt.txt", "--json"], str(tmp_path / "none.txt")),
        (["check", "--scene", tmp_path / "none.ply", "--poses", d / "gt.txt", "--images", d, "--focal", "90",
          "--json"], str(tmp_path / "none.ply")),
        (["refine", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", d, "--focal", "90", "--out",
          tmp_path / "o.txt", "--prior-error", "0", "--json"], None),
        (["evaluate", "--poses", d / "gt.txt", "--json", "--no-such-flag"], None),
    ]
    for args, file in cases:
        p = hgsloc(*args)
        assert p.returncode == 2, (args, p.stderr)
        rep = json.loads(p.stdout)
        assert set(rep) == {"error", "file", "line"} and rep["error"] and rep["file"] == file, rep
    assert "--prior-error" in json.loads(hgsloc(*cases[2][0]).stdout)["error"]


def test_evaluate_says_its_units_and_scales_them(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    plain = hgsloc("evaluate", "--poses", d / "ace.txt", "--gt", d / "gt.txt")
    assert plain.returncode == 0 and "taken as metric" in plain.stdout
    a = json.loads(hgsloc("evaluate", "--poses", d / "ace.txt", "--gt", d / "gt.txt", "--json").stdout)
    b = json.loads(hgsloc("evaluate", "--poses", d / "ace.txt", "--gt", d / "gt.txt", "--json", "--scale",
                          "0.5").stdout)
    assert a["units"]["assumed_metric"] and not b["units"]["assumed_metric"] and b["units"]["scale_to_m"] == 0.5
    assert b["median_translation_cm"] == pytest.approx(0.5 * a["median_translation_cm"])
    assert "1 scene unit = 0.5 m" in hgsloc("evaluate", "--poses", d / "ace.txt", "--gt", d / "gt.txt", "--scale",
                                             "0.5").stdout


def test_perturb_moves_each_pose_exactly_and_keeps_the_dialect(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    src = read_poses(d / "ace.txt")
    outs = []
    for k in range(2):
        outs.append(tmp_path / f"p{k}.txt")
        p = hgsloc("perturb", "--poses", d / "ace.txt", "--noise", "2cm,1deg", "--seed", "5", "--out", outs[-1])
        assert p.returncode == 0, p.stderr
    assert outs[0].read_bytes() == outs[1].read_bytes()  # deterministic per seed
    got = read_poses(outs[0])
    assert got.dialect == "ace" and list(got) == list(src)
    for n in src:
        t, r = got[n].errors_to(src[n])
        assert t == pytest.approx(0.02, abs=1e-9) and r == pytest.approx(1.0, abs=1e-6)
        assert got.record(n).tokens[8:] == src.record(n).tokens[8:]  # ACE's extra columns kept
    other = tmp_path / "q.txt"
    assert hgsloc("perturb", "--poses", d / "ace.txt", "--noise", "2cm,1deg", "--seed", "6", "--out",
                  other).returncode == 0
    assert other.read_bytes() != outs[0].read_bytes()
    qt = hgsloc("perturb", "--poses", d / "gt.txt", "--noise", "q2,t1", "--out", tmp_path / "qt.txt")
    assert qt.returncode == 0 and "q2,t1" in qt.stdout
    bad = hgsloc("perturb", "--poses", d / "gt.txt", "--noise", "2 inches", "--out", tmp_path / "x.txt")
    assert bad.returncode == 2 and "noise spec" in bad.stderr and not (tmp_path / "x.txt").exists()


def test_transforms_json_reads_as_poses_and_intrinsics_and_writes_back(tmp_path):
    from hgsloc_plugin.adapters import match_names, write_poses
    from hgsloc_plugin.adapters.intrinsics import from_query_list

    fox = shared_path("fox", "transforms.json").parent
    tj, gt = read_poses(fox / "transforms.json"), read_poses(fox / "gt.txt")
    assert tj.dialect == "transforms_json" and len(tj) == 67
    pairs = match_names(list(gt), list(tj))
    assert len(pairs) == 50
    for g, t in pairs.items():
        dt, dr = gt[g].errors_to(tj[t])
        assert dt < 1e-5 and dr < 1e-5
    # its k1 k2 p1 p2 are carried as an OPENCV distortion (the refiner undistorts the photo), unless the photos are
    # declared undistorted already (fox's are)
    lens = from_query_list(fox / "transforms.json")("images/0001.jpg", 270, 480)
    assert lens.distortion.model == "OPENCV" and lens.distortion.coeffs == (0.0578421, -0.0805099, -0.000980296,
                                                                            0.00015575)
    cam = json.loads((fox / "camera.json").read_text())
    got = from_query_list(fox / "transforms.json", allow_distortion=True)("images/0001.jpg", 270, 480)
    assert np.allclose([got.fx, got.fy, got.cx, got.cy], [cam["fx"], cam["fy"], cam["cx"], cam["cy"]])
    assert got.distortion is None and got == lens.pinhole
    # written back: the same JSON, only the refined frames' transform_matrix changed
    name = next(iter(tj))
    moved = tj[name].perturbed_in_camera([0.0, 0.01, 0.0], [0.02, 0.0, 0.0])
    out = write_poses(tmp_path / "t.json", {name: moved}, like=tj)
    a, b = json.loads((fox / "transforms.json").read_text()), json.loads(out.read_text())
    assert {k: v for k, v in a.items() if k != "frames"} == {k: v for k, v in b.items() if k != "frames"}
    assert [f for f in a["frames"][1:]] == [f for f in b["frames"][1:]]
    assert {k: v for k, v in a["frames"][0].items() if k != "transform_matrix"} == \
        {k: v for k, v in b["frames"][0].items() if k != "transform_matrix"}
    back = read_poses(out)[name]
    assert back.errors_to(moved)[0] < 1e-9 and back.errors_to(moved)[1] < 1e-6
    # evaluate matches it to the ground truth by image name
    # (its 17 frames without ground truth are named as not scored)
    p = hgsloc("evaluate", "--poses", fox / "transforms.json", "--gt", fox / "gt.txt", "--json")
    rep = json.loads(p.stdout)
    assert p.returncode == 0 and rep["n"] == 50 and rep["missing"] == 0 and rep["median_translation_cm"] < 1e-3
    assert rep["without_ground_truth"] == 17 and "17 of the 67 estimates" in p.stderr


@pytest.mark.slow
def test_refine_and_check_read_a_transforms_json(tiny_case, tmp_path):  # noqa: F811
    """A NeRF-style transforms.json of the room's priors (camera-to-world, OpenGL axes, shared intrinsics) is
    checked, refined and written back as transforms.json; the refined frames are closer to the truth."""
    from hgsloc_plugin.adapters.nerf import pose_to_c2w_gl

    d = tiny_case
    ace, gt = read_poses(d / "ace.txt"), read_poses(d / "gt.txt")
    frames = [{"file_path": f"./images/{n.replace('seq-01-', 'seq-01/')}", "transform_matrix": pose_to_c2w_gl(ace[n]),
               "note": k} for k, n in enumerate(ace)]
    src = tmp_path / "transforms.json"
    src.write_text(json.dumps({"fl_x": 90.0, "fl_y": 90.0, "cx": 64.0, "cy": 48.0, "w": 128, "h": 96,
                               "frames": frames}))
    c = hgsloc("check", "--scene", d / "scene.ply", "--poses", src, "--images", d, "--intrinsics", src)
    assert c.returncode == 0, c.stdout + c.stderr
    out = tmp_path / "refined.json"
    p = hgsloc("refine", "--scene", d / "scene.ply", "--poses", src, "--images", d, "--intrinsics", src, "--out", out,
               "--config", "fast", "--quiet")
    assert p.returncode == 0, p.stderr
    a, b = json.loads(src.read_text()), json.loads(out.read_text())
    assert [{k: v for k, v in f.items() if k != "transform_matrix"} for f in a["frames"]] == \
        [{k: v for k, v in f.items() if k != "transform_matrix"} for f in b["frames"]]
    refined = read_poses(out)
    assert refined.dialect == "transforms_json"
    for n, n_gt in zip(refined, gt):
        assert refined[n].errors_to(gt[n_gt])[0] < read_poses(src)[n].errors_to(gt[n_gt])[0]
