"""Start from what users have: a trainer's output folder, its cameras.json, and `hgsloc check` naming convention
errors (real photos and map of ../shared/data/snow, the white-background lego set)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.cli.check import check_poses
from hgsloc_plugin.core.pose import so3_exp
from hgsloc_plugin.evaluation.noise import se3_noise
from hgsloc_plugin.refine.plan import median_depth

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FLIP = np.diag([1.0, -1.0, -1.0])

#: deliberate errors: how a wrong file is made from true poses, and the reading `check` must name
ERRORS = {
    "inverted": lambda p: p.inv(),
    "OpenGL axes": lambda p: hp.Pose.from_Rt(FLIP @ p.R, FLIP @ p.tvec),
    "xyzw quaternion": lambda p: hp.Pose(np.r_[p.qvec[1:], p.qvec[0]], p.tvec),
    "scale x2": lambda p: hp.Pose(p.qvec, 2.0 * p.tvec),
}


def _dataset(name):
    d = DATA / name
    if not (d / f"{name}.ply").exists():
        pytest.skip(f"{d / (name + '.ply')} not present")
    cj = json.loads((d / "camera.json").read_text())
    cam = hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])
    pf = read_poses(d / "gt.txt", "generic")
    return d, cam, hp.GaussianScene.from_ply(d / f"{name}.ply"), {n: pf[n] for n in pf}


@pytest.mark.slow
@pytest.mark.parametrize("name", ["snow", "lego"])
def test_check_passes_true_poses_and_names_each_convention_error(name):
    d, cam, scene, gt = _dataset(name)
    bg = (1.0, 1.0, 1.0) if name == "lego" else (0.0, 0.0, 0.0)

    def run(poses):
        return check_poses(scene, poses, lambda n: d / "queries" / n, lambda n, w, h: cam, sample=4, background=bg)

    ok = run(gt)
    assert ok.verdict == "ok" and ok.ok, ok.message()
    for reading, corrupt in ERRORS.items():
        rep = run({n: corrupt(p) for n, p in gt.items()})
        assert rep.verdict == "convention error" and rep.reading == reading, (reading, rep.message())
        assert rep.hint and reading.split()[0].lower() in rep.message().lower()
    rng = np.random.default_rng(0)
    moved = hp.Pose.from_Rt(so3_exp(rng.normal(size=3) * 0.5), rng.normal(size=3))
    other = run({n: p @ moved for n, p in gt.items()})
    assert other.verdict == "disagree" and not other.ok, other.message()


@pytest.mark.slow
@pytest.mark.parametrize("name,cm,deg", [("snow", 10.0, 3.0), ("lego", 3.0, 1.0)])
def test_check_accepts_priors_a_localizer_leaves_off(name, cm, deg):
    """Priors off by a localizer's error (cm-equivalent: scaled by the median depth over 2 m): the raw costs cannot
    tell them from a wrong frame (the check used to stop `refine` on them); aligned, they agree. The same priors
    with a convention error are still named."""
    d, cam, scene, gt = _dataset(name)
    bg = (1.0, 1.0, 1.0) if name == "lego" else (0.0, 0.0, 0.0)
    rng = np.random.default_rng(3)
    noisy = {n: se3_noise(p, deg, cm / 200.0 * median_depth(scene, cam, p), rng) for n, p in gt.items()}

    def run(poses, align=True):
        return check_poses(scene, poses, lambda n: d / "queries" / n, lambda n, w, h: cam, sample=4, background=bg,
                           align=align)

    raw = run(noisy, align=False)
    assert raw.verdict != "ok" and not raw.aligned, raw.message()
    rep = run(noisy)
    assert rep.verdict == "ok", rep.message()
    assert "as given" in rep.aligned and "after aligning" in rep.message()
    assert rep.median() < 0.7 * float(np.median(rep.costs["as given"]))
    wrong = run({n: ERRORS["xyzw quaternion"](p) for n, p in noisy.items()})
    assert wrong.verdict == "convention error" and wrong.reading == "xyzw quaternion", wrong.message()


def _trainer_folder(tmp_path: Path, invert: bool = False) -> Path:
    """The Inria trainer's layout built from the snow files: two iterations, cfg_args, cameras.json."""
    d = DATA / "snow"
    out = tmp_path / "output" / "run"
    for it in (7000, 30000):
        (out / "point_cloud" / f"iteration_{it}").mkdir(parents=True)
    os.symlink(d / "snow.ply", out / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    (out / "point_cloud" / "iteration_7000" / "point_cloud.ply").write_bytes(b"not a ply")  # older: never read
    (out / "cfg_args").write_text("Namespace(sh_degree=3, source_path='/data/snow', model_path='output/run', "
                                  "images='images', resolution=-1, white_background=False, eval=True)")
    cj = json.loads((d / "camera.json").read_text())
    cams = []
    for k, line in enumerate((d / "gt.txt").read_text().splitlines()):
        t = line.split()
        p = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
        if invert:
            p = p.inv()
        cams.append({"id": k, "img_name": Path(t[0]).stem, "width": cj["width"], "height": cj["height"],
                     "position": p.centre().tolist(), "rotation": p.R.T.tolist(), "fx": cj["fx"], "fy": cj["fy"]})
    (out / "cameras.json").write_text(json.dumps(cams))
    return out


def _cli(args):
    return subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli"] + args, capture_output=True, text=True)


@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "snow" / "snow.ply").exists(), reason="../shared/data/snow not present")
def test_trainer_folder_for_check_refine_render_and_api(tmp_path):
    out = _trainer_folder(tmp_path)
    images = DATA / "snow" / "queries"
    pf = read_poses(out / "cameras.json")
    gt = read_poses(DATA / "snow" / "gt.txt", "generic")
    assert len(pf) == len(gt)
    for n in gt:
        assert pf[n].errors_to(gt[n])[0] < 1e-6 and pf[n].errors_to(gt[n])[1] < 1e-4
    common = ["--scene", str(out), "--poses", str(out / "cameras.json"), "--images", str(images),
              "--intrinsics", str(out / "cameras.json")]
    p = _cli(["check"] + common + ["--sample", "3", "--json"])
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["verdict"] == "ok"
    p = _cli(["refine"] + common + ["--out", str(tmp_path / "refined.txt"), "--config", "fast", "--limit", "1",
                                    "--quiet"])
    assert p.returncode == 0, p.stderr
    assert len(read_poses(tmp_path / "refined.txt")) == len(gt)
    cam = json.loads((DATA / "snow" / "camera.json").read_text())
    g0 = next(iter(gt.values()))
    p = _cli(["render", "--scene", str(out), "--pose", " ".join(map(str, g0.as_array())), "--camera",
              f"64 48 {cam['fx'] / 10} {cam['fy'] / 10} 32 24", "--out", str(tmp_path / "r.png")])
    assert p.returncode == 0, p.stderr
    refiner = hp.HGSLocPlugin(out)
    assert refiner.scene.source.endswith("iteration_30000/point_cloud.ply")
    assert refiner.config.background == (0.0, 0.0, 0.0)
    empty = tmp_path / "empty_run"
    empty.mkdir()
    p = _cli(["render", "--scene", str(empty), "--pose", "1 0 0 0 0 0 0", "--camera", "64 48 50 50 32 24",
              "--out", str(tmp_path / "x.png")])
    err = [ln for ln in p.stderr.splitlines() if ln.startswith("hgsloc")]
    assert p.returncode == 2 and len(err) == 1 and "point_cloud" in err[0] and "Traceback" not in p.stderr


@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "snow" / "snow.ply").exists(), reason="../shared/data/snow not present")
def test_refine_stops_on_a_convention_error_unless_skipped(tmp_path):
    out = _trainer_folder(tmp_path, invert=True)
    common = ["--scene", str(out), "--poses", str(out / "cameras.json"), "--images", str(DATA / "snow" / "queries"),
              "--intrinsics", str(out / "cameras.json"), "--config", "fast", "--limit", "1", "--quiet"]
    p = _cli(["check"] + common[:8])
    assert p.returncode == 1 and "inverted" in p.stdout and "camera-to-world" in p.stdout
    p = _cli(["refine"] + common + ["--out", str(tmp_path / "r.txt")])
    assert p.returncode == 2 and "check failed" in p.stderr and "inverted" in p.stderr
    assert not (tmp_path / "r.txt").exists()


def test_white_background_is_read_from_cfg_args(tmp_path):
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.core.scene import resolve_scene

    run = tmp_path / "run"
    (run / "point_cloud" / "iteration_100").mkdir(parents=True)
    make_room_scene(density=0.1).to_ply(run / "point_cloud" / "iteration_100" / "point_cloud.ply")
    (run / "cfg_args").write_text("Namespace(white_background=True, sh_degree=3)")
    ply, white = resolve_scene(run)
    assert ply.name == "point_cloud.ply" and white is True
    assert hp.HGSLocPlugin(run).config.background == (1.0, 1.0, 1.0)
    assert hp.HGSLocPlugin(run, hp.RefineConfig()).config.background == (0.0, 0.0, 0.0)  # explicit config wins


def test_a_reading_that_renders_a_sliver_is_no_match():
    """A reading whose rendering covers 16 pixels, similar there (a quaternion read x y z w on snow, 2 % / 1 deg
    priors), scored 0.03 and passed for the right reading: now its similarity is spread over at least ``MIN_COVER``
    of the best-covered reading's pixels; readings that cover as much are scored as before."""
    from hgsloc_plugin.cli.check import MIN_COVER, covered_cost

    sums = np.array([[11195.4, 27723.0], [15.5, 16.0], [0.0, 0.0]])
    cover = MIN_COVER * sums[:, 1].max()
    c = covered_cost(sums, cover)
    assert c[0] == pytest.approx(1 - 11195.4 / 27723.0) and c[1] > 0.99 and c[2] == 1.0
