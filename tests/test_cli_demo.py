"""End to end: CLI refine -> evaluate round trip with resume, render, errors, the demo, noise protocols."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.adapters import read_poses
from hgsloc_plugin.adapters.confidence import MEDIAN_DEG, Q99_DEG, REGION_MARGIN
from hgsloc_plugin.cli.demo.queries import query_poses
from hgsloc_plugin.cli.demo.scene import make_room_scene
from hgsloc_plugin.cli.parser import main
from hgsloc_plugin.evaluation.noise import parse_protocol, qt_noise, qt_noise_raw, se3_noise
from hgsloc_plugin.evaluation.viz import save_png


@pytest.fixture(scope="module")
def tiny_case(tmp_path_factory):
    """A small room scene on disk, 3 queries as PNGs, GT and ACE-dialect coarse poses."""
    d = tmp_path_factory.mktemp("case")
    scene = make_room_scene(density=0.35)
    scene.to_ply(d / "scene.ply")
    cam = hp.Camera.from_focal(128, 96, 90.0)
    gts = query_poses(3, seed=11)
    imgs = hp.render(scene, cam, gts)
    (d / "images" / "seq-01").mkdir(parents=True)
    rng = np.random.default_rng(1)
    gt_lines, ace_lines = [], []
    for k, (g, im) in enumerate(zip(gts, imgs)):
        name = f"seq-01/frame-{k:06d}.color.png"
        save_png(im, d / "images" / name)
        c = se3_noise(g, 1.0, 0.03, rng)
        gt_lines.append(" ".join([name] + [repr(float(v)) for v in g.as_array()]))
        ace_lines.append(" ".join([name.replace("/", "-")] + [repr(float(v)) for v in c.as_array()] + ["1.0", "0.03",
                                                                                                      "500"]))
    (d / "gt.txt").write_text("\n".join(gt_lines) + "\n")
    (d / "ace.txt").write_text("\n".join(ace_lines) + "\n")
    return d


@pytest.mark.slow
def test_cli_refine_evaluate_and_resume(tiny_case, capsys):
    d = tiny_case
    out = d / "refined.txt"
    args = ["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images", str(d / "images"),
            "--focal", "90", "--out", str(out), "--config", "fast", "--quiet", "--limit", "2"]
    assert main(args) == 0
    rep = json.loads((d / "refined.txt.json").read_text())
    assert len(rep["queries"]) == 2 and rep["dialect"] == "ace"
    # the ACE file's inlier counts (500: a doubtful pose) set each query's rotation bound; --no-inlier-region not
    assert [q["max_rotation_deg"] for q in rep["queries"].values()] == [pytest.approx(REGION_MARGIN * Q99_DEG[0])] * 2
    assert [q["prior_error_deg"] for q in rep["queries"].values()] == [pytest.approx(MEDIAN_DEG[0])] * 2
    assert main(args[:-1] + ["1", "--out", str(d / "plain.txt"), "--no-inlier-region", "--skip-check",
                             "--prior-error", "5cm", "--prior-rotation-error", "2deg"]) == 0
    plain = json.loads((d / "plain.txt.json").read_text())
    q_plain = list(plain["queries"].values())[0]
    assert q_plain["max_rotation_deg"] != pytest.approx(REGION_MARGIN * Q99_DEG[0])
    assert (q_plain["prior_error"], q_plain["prior_error_deg"]) == (pytest.approx(0.05), 2.0)
    assert (plain["config"]["prior_error"], plain["config"]["prior_error_deg"]) == (pytest.approx(0.05), 2.0)
    capsys.readouterr()
    assert main(args[:-1] + ["1", "--out", str(d / "bad.txt"), "--prior-error", "far"]) == 2
    assert "--prior-error" in capsys.readouterr().err and not (d / "bad.txt").exists()
    assert read_poses(out).dialect == "ace" and len(read_poses(out)) == 3
    # resume: the third query is refined, the first two are not redone, no duplicate lines
    args_all = [a for a in args if a not in ("--limit", "2")]
    assert main(args_all) == 0
    rep2 = json.loads((d / "refined.txt.json").read_text())
    assert len(rep2["queries"]) == 3
    for n in list(rep["queries"]):
        assert rep2["queries"][n] == rep["queries"][n]
    lines = out.read_text().splitlines()
    assert len(lines) == 3 and len({ln.split()[0] for ln in lines}) == 3
    capsys.readouterr()
    assert main(["evaluate", "--poses", str(out), "--gt", str(d / "gt.txt"), "--json"]) == 0
    after = json.loads(capsys.readouterr().out)
    assert main(["evaluate", "--poses", str(d / "ace.txt"), "--gt", str(d / "gt.txt"), "--json"]) == 0
    before = json.loads(capsys.readouterr().out)
    assert set(after) >= {"n", "missing", "median_translation_cm", "median_rotation_deg", "recall"}
    assert after["n"] == 3 and after["missing"] == 0
    assert after["median_translation_cm"] < before["median_translation_cm"] / 2
    est, gt = read_poses(out), read_poses(d / "gt.txt")
    errs = [est[n.replace("/", "-")].errors_to(g) for n, g in gt.items()]
    assert after["recall"]["1cm1deg"] == pytest.approx(np.mean([t < 0.01 and r < 1.0 for t, r in errs]))
    assert after["recall"]["5cm5deg"] == pytest.approx(np.mean([t < 0.05 and r < 5.0 for t, r in errs]))


@pytest.mark.slow
def test_cli_user_errors_are_one_line(tiny_case, tmp_path):
    d = tiny_case
    cases = [
        ["refine", "--scene", str(d / "missing.ply"), "--poses", str(d / "ace.txt"), "--images", str(d),
         "--focal", "90", "--out", str(tmp_path / "o.txt")],
        ["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images", str(d),
         "--focal", "90", "--out", str(d / "ace.txt")],
        ["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images", str(d),
         "--out", str(tmp_path / "o.txt")],
        ["evaluate", "--poses", str(d / "gt.txt"), "--gt", str(tmp_path / "nope.txt")],
        ["render", "--scene", str(d / "scene.ply"), "--pose", "1 0 0", "--camera", "64 48 50 50 32 24",
         "--out", str(tmp_path / "x.png")],
        ["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images", str(d),
         "--focal", "90", "--out", str(tmp_path / "o.txt"), "--limit", "-2"],
        ["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images", str(d),
         "--focal", "90", "--out", str(tmp_path / "o.txt"), "--prior-error", "0"],
    ]
    before = (d / "ace.txt").read_bytes()
    errors = []
    for c in cases:
        p = subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli"] + c, capture_output=True, text=True)
        assert p.returncode == 2, (c, p.stderr)
        err = [ln for ln in p.stderr.splitlines() if ln.startswith("hgsloc")]
        assert len(err) == 1 and "Traceback" not in p.stderr, p.stderr
        errors.append(err[0])
    assert (d / "ace.txt").read_bytes() == before and not (tmp_path / "o.txt").exists()
    # a negative --limit is refused (a slice would refine all but the last two); a message ending in a quoted
    # value keeps its closing quote
    assert "--limit: expected a whole number >= 0, got '-2'" in errors[-2]
    for args, msg in ((["demo", "--queries", "0"], "--queries: expected a whole number >= 1, got '0'"),
                      (["check", "--scene", "s.ply", "--poses", "p.txt", "--images", ".", "--sample", "x"],
                       "--sample: expected a whole number >= 1, got 'x'")):
        p = subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli"] + args, capture_output=True, text=True)
        assert p.returncode == 2 and msg in p.stderr, p.stderr
    assert errors[-1].endswith("--prior-error: must be > 0, got '0'")


def test_cli_render(tiny_case, tmp_path):
    from PIL import Image

    out = tmp_path / "r.png"
    T = query_poses(1, seed=11)[0]
    pose = " ".join(repr(float(v)) for v in T.as_array())
    assert main(["render", "--scene", str(tiny_case / "scene.ply"), "--pose", pose, "--camera",
                 "128 96 90 90 64 48", "--out", str(out)]) == 0
    a = np.asarray(Image.open(out), dtype=np.float32) / 255
    b = np.asarray(Image.open(tiny_case / "images" / "seq-01" / "frame-000000.color.png"), dtype=np.float32) / 255
    assert a.shape == (96, 128, 3) and np.abs(a - b).max() < 1.5 / 255


@pytest.mark.slow
def test_hloc_step(tiny_case, tmp_path):
    from hgsloc_plugin import hloc_step as step

    d = tiny_case
    q = tmp_path / "queries_with_intrinsics.txt"
    q.write_text("".join(f"seq-01/frame-{k:06d}.color.png SIMPLE_PINHOLE 128 96 90 64 48\n" for k in range(3)))
    res = tmp_path / "results.txt"
    ace = read_poses(d / "ace.txt")
    res.write_text("".join(" ".join([n.replace("seq-01-", "seq-01/")] + r.tokens[1:8]) + "\n"
                           for n, r in ((n, ace.record(n)) for n in ace)))
    out = step.main(d / "scene.ply", q, res, d / "images", tmp_path / "results_refined.txt",
                    hp.RefineConfig.preset("fast"), limit=1)
    pf = read_poses(out)
    assert pf.dialect == "hloc" and list(pf) == list(read_poses(res))
    # from the shell, as a pipeline script runs it, with the localizer's typical error declared: each refined pose
    # is fused with its prior and the report records the error; a bad value exits 2 naming the flag, writes nothing
    base = [sys.executable, "-m", "hgsloc_plugin.hloc_step", "--scene", str(d / "scene.ply"), "--queries", str(q),
            "--results", str(res), "--image_dir", str(d / "images"), "--config", "fast", "--limit", "2"]
    shell_out = tmp_path / "shell_refined.txt"
    run = subprocess.run(base + ["--output", str(shell_out), "--prior_error", "5cm", "--prior_rotation_error", "2deg",
                                 "--batch_size", "2", "--lod_pixels", "2", "--map_floor", "0.5%,0.2deg"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    rep = json.loads(shell_out.with_name(shell_out.name + ".json").read_text())
    assert rep["config"]["prior_error"] == pytest.approx(0.05) and rep["config"]["prior_error_deg"] == 2.0
    assert rep["config"]["tuning"]["lod_pixels"] == 2.0
    assert rep["config"]["tuning"]["map_floor_depth"] == pytest.approx(0.005)
    assert rep["config"]["tuning"]["map_floor_deg"] == pytest.approx(0.2)
    entries = list(rep["queries"].values())
    assert len(entries) == 2 and rep["totals"]["accepted"] >= 1
    assert all(e["fused"] == e["accepted"] and e["prior_error"] == pytest.approx(0.05) for e in entries)
    bad = subprocess.run(base + ["--output", str(tmp_path / "bad.txt"), "--prior_error", "5 parsecs"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "--prior_error" in bad.stderr and not (tmp_path / "bad.txt").exists()
    bad = subprocess.run(base + ["--output", str(tmp_path / "bad.txt"), "--batch_size", "0"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "--batch_size" in bad.stderr and not (tmp_path / "bad.txt").exists()
    bad = subprocess.run(base + ["--output", str(tmp_path / "bad.txt"), "--lod_pixels", "-1"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "--lod_pixels" in bad.stderr and not (tmp_path / "bad.txt").exists()
    bad = subprocess.run(base + ["--output", str(tmp_path / "bad.txt"), "--map_floor", "0.5"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "--map_floor" in bad.stderr and not (tmp_path / "bad.txt").exists()
    # a damaged line in hloc's results is an error naming it (not a line skipped as if the file were Marepo's)
    damaged = tmp_path / "damaged.txt"
    damaged.write_text(res.read_text() + "garbage line here\n")
    run = subprocess.run(base + ["--results", str(damaged), "--output", str(tmp_path / "d.txt")],
                         capture_output=True, text=True)
    assert run.returncode == 2 and "damaged.txt:4: expected 8 columns" in run.stderr, run.stderr
    assert not (tmp_path / "d.txt").exists()


@pytest.mark.slow
def test_demo_runs_and_improves(tmp_path):
    from hgsloc_plugin.cli.demo.run import run_demo

    t0 = time.perf_counter()
    s = run_demo(tmp_path / "demo", queries=3, noise=("3cm,1deg",), preset="fast", progress=False)
    wall = time.perf_counter() - t0
    row = s["rows"][0]
    # s/query is the file's time over its queries, not each query's own time (those overlap in a lockstep batch)
    assert 0 < 3 * row["seconds_per_query"] <= wall
    assert row["after"]["median_translation_cm"] < row["before"]["median_translation_cm"]
    assert row["after"]["median_rotation_deg"] < row["before"]["median_rotation_deg"]
    figs = sorted(p.name for p in (tmp_path / "demo" / "figures").iterdir())
    assert any(f.startswith("compare_") for f in figs) and any(f.startswith("errors_") for f in figs)
    assert any(f.startswith("cost_") for f in figs)  # the polish ran: its stages are plotted
    from PIL import Image

    comp = Image.open(next((tmp_path / "demo" / "figures").glob("compare_*")))
    assert comp.size[0] > 2 * 320 * 0.9 and comp.size[1] > 2 * 240 * 0.9  # four panels of the 320x240 query
    assert (tmp_path / "demo" / "refined_3cm_1deg.txt.json").exists()


def test_demo_scene_is_deterministic(tmp_path):
    a = make_room_scene(seed=3, density=0.2).to_ply(tmp_path / "a.ply").read_bytes()
    b = make_room_scene(seed=3, density=0.2).to_ply(tmp_path / "b.ply").read_bytes()
    assert a == b
    assert make_room_scene(density=1.0).num_gaussians > 20000
    assert make_room_scene(density=0.2).sh_degree >= 1


def test_noise_protocols_have_exact_magnitudes():
    rng = np.random.default_rng(0)
    T = query_poses(1, seed=0)[0]
    for deg, d in ((0.5, 0.01), (3.0, 0.1)):
        for _ in range(5):
            N = se3_noise(T, deg, d, rng)
            dt, dr = N.errors_to(T)
            assert dt == pytest.approx(d, abs=1e-12) and dr == pytest.approx(deg, abs=1e-9)
    for _ in range(5):
        state = rng.bit_generator.state
        q, t = qt_noise_raw(T, 2, 1, rng)
        kq, kt = (q - T.qvec) * 100, (t - T.tvec) * 10
        np.testing.assert_allclose(kq, np.round(kq), atol=1e-9)
        np.testing.assert_allclose(kt, np.round(kt), atol=1e-9)
        assert np.all(np.abs(np.round(kq)) <= 9) and np.all(np.abs(np.round(kt)) <= 9)
        rng.bit_generator.state = state
        N = qt_noise(T, 2, 1, rng)
        assert N == hp.Pose(q, t) and np.linalg.norm(N.qvec) == pytest.approx(1.0)
    assert parse_protocol("q2,t1") == ("qt", 2, 1)
    assert parse_protocol("3cm,1deg") == ("se3", 0.03, 1.0)
    assert parse_protocol("0.1m,2deg")[1] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="banana"):
        parse_protocol("banana")
    assert parse_protocol("q3_t3") == ("qt", 3, 3)


@pytest.mark.slow
def test_cli_refine_writes_figures(tiny_case, tmp_path):
    from PIL import Image

    d = tiny_case
    figs = tmp_path / "figs"
    assert main(["refine", "--scene", str(d / "scene.ply"), "--poses", str(d / "ace.txt"), "--images",
                 str(d / "images"), "--focal", "90", "--out", str(tmp_path / "r.txt"), "--config", "fast",
                 "--limit", "1", "--quiet", "--figures", str(figs)]) == 0
    pngs = list(figs.glob("*.png"))
    assert len(pngs) == 1 and pngs[0].name == "seq-01-frame-000000.color.png"  # not .png.png
    assert min(Image.open(pngs[0]).size) > 2 * 96 * 0.9  # four panels of the 128x96 query


@pytest.mark.slow
def test_cli_gradient_preset_and_no_polish(tiny_case, tmp_path):
    """As a user runs it: --config gradient refines with derivative passes only; --no-polish turns the polish off."""
    d = tiny_case
    base = [sys.executable, "-m", "hgsloc_plugin.cli", "refine", "--scene", str(d / "scene.ply"), "--poses",
            str(d / "ace.txt"), "--images", str(d / "images"), "--focal", "90", "--quiet", "--limit", "1"]
    reports = {}
    for name, extra in (("gradient", ["--config", "gradient"]), ("nopolish", ["--config", "fast", "--no-polish"])):
        out = tmp_path / f"{name}.txt"
        p = subprocess.run(base + ["--out", str(out)] + extra, capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        reports[name] = next(iter(json.loads(Path(str(out) + ".json").read_text())["queries"].values()))
    g, n = reports["gradient"], reports["nopolish"]
    assert g["expansions"] == 0 and g["derivative_passes"] >= 2 and len(g["polish"]) >= 2
    assert len(g["polish"][-1]["jtj"]) == 6
    assert n["derivative_passes"] == 0 and n["polish"] == [] and n["expansions"] > 0


@pytest.mark.slow
def test_cli_lod_pixels_reaches_the_config_and_is_checked(tiny_case, tmp_path):
    """--lod-pixels 2 sets Tuning.lod_pixels (the report's config says so); 0 is refused naming the flag, in JSON
    with --json, nothing written."""
    d = tiny_case
    base = [sys.executable, "-m", "hgsloc_plugin.cli", "refine", "--scene", str(d / "scene.ply"), "--poses",
            str(d / "ace.txt"), "--images", str(d / "images"), "--focal", "90", "--quiet", "--limit", "1"]
    out = tmp_path / "lod.txt"
    p = subprocess.run(base + ["--out", str(out), "--lod-pixels", "2px"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert json.loads(Path(str(out) + ".json").read_text())["config"]["tuning"]["lod_pixels"] == 2.0
    bad = tmp_path / "bad.txt"
    p = subprocess.run(base + ["--out", str(bad), "--lod-pixels", "0", "--json"], capture_output=True, text=True)
    assert p.returncode == 2 and not bad.exists()
    assert json.loads(p.stdout)["error"] == "--lod-pixels: must be > 0, got '0'"


def test_pose_file_limit_must_be_a_count(tiny_case, tmp_path):
    """refine_pose_file(limit=-2) would slice off the last two queries and refine the rest: refused, nothing
    written."""
    from hgsloc_plugin.adapters.intrinsics import from_focal
    from hgsloc_plugin.run.pipeline import refine_pose_file

    d = tiny_case
    with pytest.raises(ValueError, match="limit must be >= 0"):
        refine_pose_file(d / "scene.ply", d / "ace.txt", d / "images", from_focal(90.0), tmp_path / "o.txt", limit=-2)
    assert not (tmp_path / "o.txt").exists()
