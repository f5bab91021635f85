"""Output a user can trust, run as a user runs it (subprocesses): a resume checks what it resumes, an interrupted run
leaves nothing that passes for a result, evaluate scores what both files hold, units for maps of any scale,
wall-clock timings, and the small things a first run meets (notices, figures, examples)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hgsloc_plugin.adapters import read_poses

from .test_cli_contracts import hgsloc, refine_args
from .test_cli_demo import tiny_case  # noqa: F401  (module-scoped fixture shared with the CLI tests)

ROOT = Path(__file__).resolve().parents[1]


def report(out: Path) -> dict:
    return json.loads(Path(str(out) + ".json").read_text())


def project_depth(scene_path, pose, focal: float, w: int, h: int) -> float:
    """Median camera z of the Gaussian centres inside a centred-focal image: the depth, written out here."""
    from hgsloc_plugin import GaussianScene

    p = GaussianScene.from_ply(scene_path).means.astype(np.float64) @ pose.R.T + pose.tvec
    z = p[:, 2]
    front = z > 1e-6
    u, v = focal * p[front, 0] / z[front] + w / 2, focal * p[front, 1] / z[front] + h / 2
    return float(np.median(z[front][(u >= 0) & (u < w) & (v >= 0) & (v < h)]))


@pytest.mark.slow
def test_a_resume_of_other_inputs_is_refused_and_changed_queries_are_recomputed(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    out = tmp_path / "o.txt"
    first = hgsloc(*refine_args(d, out, "--limit", "2"))
    assert first.returncode == 0, first.stderr
    before = report(out)
    assert before["complete"] and set(before["fingerprint"]) == {"scene", "config", "raster", "dialect"}
    text = out.read_text()
    # another preset, another map: one line naming what changed and --restart; nothing touched
    other = hgsloc(*[a if a != "fast" else "default" for a in refine_args(d, out)])
    assert other.returncode == 2 and "refinement settings" in other.stderr and "--restart" in other.stderr
    assert len([ln for ln in other.stderr.splitlines() if ln.startswith("hgsloc")]) == 1, other.stderr
    from hgsloc_plugin.cli.demo.scene import make_room_scene

    make_room_scene(density=0.3).to_ply(tmp_path / "other.ply")
    args = refine_args(d, out)
    args[args.index("--scene") + 1] = tmp_path / "other.ply"
    moved = hgsloc(*args)
    assert moved.returncode == 2 and "map's content (--scene)" in moved.stderr
    assert out.read_text() == text and report(out) == before
    # the same map from another path is the same map: resumed (the third query refined, the two others kept)
    shutil.copy(d / "scene.ply", tmp_path / "copy.ply")
    args[args.index("--scene") + 1] = tmp_path / "copy.ply"
    again = hgsloc(*args)
    assert again.returncode == 0, again.stderr
    after = report(out)
    assert after["resumed"] == {"done": 2, "of": 3, "recomputed": 0, "retried": 0}
    for n in before["queries"]:
        assert after["queries"][n] == before["queries"][n]
    # another prior for one query: that one is recomputed, the others reused bit for bit
    priors = (d / "ace.txt").read_text().splitlines()
    tok = priors[1].split()
    tok[5] = repr(float(tok[5]) + 0.01)
    priors[1] = " ".join(tok)
    (tmp_path / "ace2.txt").write_text("\n".join(priors) + "\n")
    changed = refine_args(d, out)
    changed[changed.index("--poses") + 1] = tmp_path / "ace2.txt"
    third = hgsloc(*changed)
    assert third.returncode == 0, third.stderr
    rep = report(out)
    assert rep["resumed"] == {"done": 2, "of": 3, "recomputed": 1, "retried": 0}
    assert "recomputing 1 whose inputs changed" in third.stderr
    name = tok[0]
    assert rep["queries"][name] != after["queries"][name] and rep["input"] == str(tmp_path / "ace2.txt")
    assert all(rep["queries"][n] == after["queries"][n] for n in rep["queries"] if n != name)
    new_lines = {ln.split()[0]: ln for ln in out.read_text().splitlines()}
    old_lines = {ln.split()[0]: ln for ln in text.splitlines()}
    assert all(new_lines[n] == old_lines[n] for n in list(before["queries"]) if n != name)  # same bytes
    # --restart starts over on other settings
    restarted = hgsloc(*[a if a != "fast" else "gradient" for a in refine_args(d, out)], "--restart")
    assert restarted.returncode == 0, restarted.stderr
    assert report(out)["resumed"] is None and report(out)["config"]["routes"] == "gradient"


INTERRUPT_AFTER_FIRST = """
import os, signal, sys
import hgsloc_plugin.run.pipeline as pipeline
from hgsloc_plugin.cli import main
# a shell runs a background job's children with SIGINT ignored (a suite run as `pytest ... &`); a user's terminal
# delivers it: Python's own handler, which raises KeyboardInterrupt
signal.signal(signal.SIGINT, signal.default_int_handler)
real = pipeline.run_batch
def run_batch(*args, on_result, **kw):
    def first(q, res):
        on_result(q, res)
        os.kill(os.getpid(), signal.SIGINT)  # a user's Ctrl-C once the first query is done
    return real(*args, on_result=first, **kw)
pipeline.run_batch = run_batch
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_an_interrupted_run_leaves_no_pose_file_and_evaluate_refuses_it(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    out = tmp_path / "o.txt"
    args = [str(a) for a in refine_args(d, out, "--batch-size", "1")]
    p = subprocess.run([sys.executable, "-c", INTERRUPT_AFTER_FIRST, *args], capture_output=True, text=True)
    assert p.returncode == 130, p.stderr
    assert "interrupted; rerun the same command to resume" in p.stderr
    assert not out.exists()  # the priors never pass for output
    rep = report(out)
    assert rep["complete"] is False and rep["totals"]["queries"] >= 1
    ev = hgsloc("evaluate", "--poses", out, "--gt", d / "gt.txt", "--json")
    assert ev.returncode == 2 and "has not completed" in json.loads(ev.stdout)["error"]
    # an earlier complete result does not survive a rerun that is interrupted: no stale pose file
    done = hgsloc(*refine_args(d, out))
    assert done.returncode == 0 and report(out)["complete"] and out.exists()
    assert hgsloc("evaluate", "--poses", out, "--gt", d / "gt.txt").returncode == 0
    again = [a if a != "fast" else "gradient" for a in args] + ["--restart"]
    p = subprocess.run([sys.executable, "-c", INTERRUPT_AFTER_FIRST, *again], capture_output=True, text=True)
    assert p.returncode == 130 and not out.exists() and report(out)["complete"] is False


@pytest.mark.slow
def test_summaries_give_wall_clock_seconds(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    out = tmp_path / "o.txt"
    p = hgsloc(*refine_args(d, out, "--batch-size", "3"))
    assert p.returncode == 0, p.stderr
    t = report(out)["totals"]
    # three queries refined together: each one's own time spans most of the batch, the wall far less than the sum
    assert 0 < t["wall_seconds"] < t["query_seconds"]
    assert t["seconds_per_query"] == pytest.approx(t["wall_seconds"] / 3, abs=1e-3)
    assert f"{t['wall_seconds']:.1f} s wall, {t['seconds_per_query']:.2f} s/query" in p.stdout
    resumed = hgsloc(*refine_args(d, out))
    this_run, in_all = resumed.stdout.splitlines()
    assert "/ 0 queries" in this_run and "s/query" not in this_run and "0.00 s/query" not in resumed.stdout
    both = report(out)["totals"]  # the runs' walls add up
    assert both["wall_seconds"] >= t["wall_seconds"] and f"{both['seconds_per_query']:.2f} s/query" in in_all


def test_evaluate_scores_the_names_both_files_hold(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    lines = (d / "gt.txt").read_text().splitlines()
    (tmp_path / "two.txt").write_text("\n".join(lines[:2]) + "\n")
    p = hgsloc("evaluate", "--poses", tmp_path / "two.txt", "--gt", d / "gt.txt", "--json")
    r = json.loads(p.stdout)
    assert p.returncode == 0 and r["n"] == 2 and r["missing"] == 1 and r["median_translation_cm"] == 0.0
    assert r["recall"]["1cm1deg"] == 1.0 and "1 of the 3 images" in p.stderr and "not scored" in p.stderr
    strict = json.loads(hgsloc("evaluate", "--poses", tmp_path / "two.txt", "--gt", d / "gt.txt", "--json",
                               "--missing-as-failure").stdout)
    assert strict["n"] == 3 and strict["recall"]["1cm1deg"] == pytest.approx(2 / 3)
    # an estimate without ground truth is named as an error, not scored
    extra = lines[0].replace("frame-000000", "frame-000099")
    (tmp_path / "more.txt").write_text("\n".join(lines + [extra]) + "\n")
    p = hgsloc("evaluate", "--poses", tmp_path / "more.txt", "--gt", d / "gt.txt", "--json")
    r = json.loads(p.stdout)
    assert r["n"] == 3 and r["without_ground_truth"] == 1
    assert "error: 1 of the 4 estimates" in p.stderr and "frame-000099" in p.stderr


@pytest.mark.slow
def test_perturb_by_a_share_of_the_depth_and_check_says_the_scale(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    out = tmp_path / "p.txt"
    p = hgsloc("perturb", "--poses", d / "gt.txt", "--noise", "2%,1deg", "--seed", "3", "--out", out, "--scene",
               d / "scene.ply", "--images", d / "images", "--focal", "90")
    assert p.returncode == 0, p.stderr
    gt, moved = read_poses(d / "gt.txt"), read_poses(out)
    depths = []
    for n, g in gt.items():
        depths.append(project_depth(d / "scene.ply", g, 90.0, 128, 96))
        dt, dr = moved[n].errors_to(g)
        assert dt == pytest.approx(0.02 * depths[-1], rel=1e-9) and dr == pytest.approx(1.0, abs=1e-9)
    assert "2 % of its median depth" in p.stdout
    bare = hgsloc("perturb", "--poses", d / "gt.txt", "--noise", "2%,1deg", "--out", tmp_path / "q.txt")
    assert bare.returncode == 2 and "--scene, --images" in bare.stderr and not (tmp_path / "q.txt").exists()
    c = hgsloc("check", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", d / "images", "--focal",
               "90", "--json")
    rep = json.loads(c.stdout)
    assert rep["median_depth"] == pytest.approx(float(np.median(depths)), rel=1e-9)
    assert rep["scale_for_2m"] == pytest.approx(2.0 / rep["median_depth"])
    text = hgsloc("check", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", d / "images", "--focal",
                  "90").stdout
    assert f"median depth {rep['median_depth']:.4g} scene units" in text
    assert f"--scale {rep['scale_for_2m']:.3g}" in text


@pytest.mark.slow
def test_missing_inputs_are_named_once(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    p = hgsloc(*refine_args(d, tmp_path / "o.txt", images=tmp_path / "nowhere"))
    assert p.returncode == 2 and p.stderr.count("nowhere") == 1 and "image folder not found" in p.stderr
    assert not (tmp_path / "o.txt").exists()
    imgs = tmp_path / "images"
    shutil.copytree(d / "images", imgs)
    (imgs / "seq-01" / "frame-000002.color.png").unlink()
    args = [a for a in refine_args(d, tmp_path / "o.txt", images=imgs) if a != "--skip-check"]
    p = hgsloc(*args)
    assert p.returncode == 3
    named = [ln for ln in p.stderr.splitlines() if "frame-000002" in ln]
    assert len(named) == 1 and "(tried 9 names: " in named[0], p.stderr  # the failure line, no warnings before it


def test_intrinsics_from_a_camera_json_and_rescaling_said_once(tmp_path, caplog):
    from hgsloc_plugin.adapters.intrinsics import from_query_list

    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps({"width": 198, "height": 148, "fx": 163.8, "fy": 163.9, "cx": 99.0, "cy": 74.0}))
    fn = from_query_list(cam)
    with caplog.at_level("WARNING", logger="hgsloc_plugin"):
        a, b = fn("a.png", 198, 148), fn("b.png", 99, 74)
        fn("c.png", 99, 74)
    assert (a.fx, a.fy, a.cx) == (163.8, 163.9, 99.0) and (b.width, b.fx, b.cx) == (99, 81.9, 49.5)
    said = [r.getMessage() for r in caplog.records if "scaled to each photo" in r.getMessage()]
    assert len(said) == 1 and "198x148" in said[0] and "99x74" in said[0]
    cam.write_text(json.dumps({"width": 198, "height": 148, "fx": 160, "fy": 160, "cx": 99, "cy": 74,
                               "model": "OPENCV", "params": [-0.25, 0.08, 0, 0]}))
    assert from_query_list(cam)("a.png", 198, 148).distortion.coeffs == (-0.25, 0.08, 0.0, 0.0)
    cam.write_text(json.dumps({"width": 198, "fx": 160}))
    with pytest.raises(ValueError, match=r"camera.json: a camera JSON needs .* missing height, fy, cx, cy"):
        from_query_list(cam)


def test_first_run_says_the_kernels_compile(tmp_path, monkeypatch, caplog):
    from hgsloc_plugin.core import backend

    code = ("import logging; logging.basicConfig(); from hgsloc_plugin.core import backend; "
            "backend.compile_notice('cpu', 3)")
    env = {**__import__("os").environ, "HGSLOC_CACHE_DIR": str(tmp_path)}
    first = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    second = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert "first run on this machine (cpu, 3 threads)" in first.stderr and "compile" in first.stderr
    assert second.stderr == ""  # the first process marked this cache warm for this thread count
    monkeypatch.setenv("HGSLOC_CACHE_DIR", str(tmp_path))
    with caplog.at_level("WARNING", logger="hgsloc_plugin"):
        backend.compile_notice("cpu", 5)  # another thread count compiles its own set
    assert "5 threads" in caplog.text


def test_figures_are_labelled_and_fit_portrait_images(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.viz import comparison_panels, cost_figure

    scene = make_room_scene(density=0.2)
    cam = hp.Camera.from_fov(60, 80, 50.0)  # portrait
    gt = query_poses(1, seed=2)[0]
    fig = comparison_panels(scene, cam, hp.render(scene, cam, gt), gt, gt)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    boxes = [a.title.get_window_extent(r) for a in fig.axes[:4]]
    assert not boxes[0].overlaps(boxes[1]) and not boxes[2].overlaps(boxes[3])
    entry = {"cost_initial": 0.5, "levels": [], "polish": [{"width": 60, "height": 80, "cost_start": 0.5,
                                                            "cost": 0.3}]}
    fig = cost_figure([entry, entry], names=["q1.png", "q2.png"])
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["q1.png", "q2.png"]


@pytest.mark.slow
def test_figure_files_are_named_once(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    p = hgsloc("check", "--scene", d / "scene.ply", "--poses", d / "gt.txt", "--images", d / "images", "--focal",
               "90", "--figures", tmp_path / "f", "--sample", "1")
    assert p.returncode == 0, p.stderr
    names = sorted(f.name for f in (tmp_path / "f").iterdir())
    assert names == ["seq-01_frame-000000.color.check.png"]


@pytest.mark.parametrize("script", ["refine_ace_7scenes.py", "refine_marepo_7scenes.py", "hloc_pipeline_step.py"])
def test_examples_name_a_missing_layout_without_a_traceback(script, tmp_path):
    path = ROOT / "examples" / script
    h = subprocess.run([sys.executable, path, "--help"], capture_output=True, text=True)
    assert h.returncode == 0 and "--dataset" in h.stdout and "--maps" in h.stdout and "point_cloud.ply" in h.stdout
    if "marepo" in script:
        assert "Marepo's" in h.stdout and "ACE's" not in h.stdout
    extra = ["--outputs", tmp_path] if "hloc" in script else []
    p = subprocess.run([sys.executable, path, "--dataset", tmp_path / "ds", "--maps", tmp_path / "maps", *extra],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "not found" in p.stderr, p.stderr


@pytest.mark.slow
def test_the_hloc_step_names_its_own_flags_and_failed_queries(tiny_case, tmp_path):  # noqa: F811
    d = tiny_case
    q = tmp_path / "queries_with_intrinsics.txt"
    q.write_text("".join(f"seq-01/frame-{k:06d}.color.png SIMPLE_RADIAL 128 96 90 64 48 0.002\n" for k in range(3)))
    ace = read_poses(d / "ace.txt")
    res = tmp_path / "results.txt"
    res.write_text("".join(" ".join([n.replace("seq-01-", "seq-01/")] + ace.record(n).tokens[1:8]) + "\n"
                           for n in ace))
    imgs = tmp_path / "images"
    shutil.copytree(d / "images", imgs)
    (imgs / "seq-01" / "frame-000002.color.png").unlink()
    base = [sys.executable, "-m", "hgsloc_plugin.hloc_step", "--scene", d / "scene.ply", "--queries", q, "--results",
            res, "--image_dir", imgs, "--config", "fast", "--output", tmp_path / "out.txt", "--no_inlier_region"]
    p = subprocess.run(base, capture_output=True, text=True)
    assert p.returncode == 3, p.stderr
    assert "undistorting the query photos (SIMPLE_RADIAL k=0.002)" in p.stderr and "--allow_distortion" in p.stderr
    assert "--allow-distortion" not in p.stderr
    assert "hloc step: failed: seq-01/frame-000002.color.png" in p.stderr
    other = subprocess.run([a if a != "fast" else "gradient" for a in base], capture_output=True, text=True)
    assert other.returncode == 2 and "refinement settings" in other.stderr and "rerun with --restart" in other.stderr
