"""The map's floor (``evaluation/floor.py``, ``hgsloc check --measure-floor``, ``hgsloc refine --map-floor``): the
offsets of the map's minima from views with known poses, as the floor in every polished pose's covariance."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import hgsloc_plugin as hp
from hgsloc_plugin.core.units import parse_angle, parse_map_floor
from hgsloc_plugin.evaluation.floor import cost_bound, floor_from_offsets, map_floor, t_quantile

ROOT = Path(__file__).resolve().parents[1]


def test_floor_is_the_root_mean_square_and_leaves_a_view_out():
    offsets = np.array([[0.01, 0.3], [0.002, 0.1], [0.004, 0.2]])
    f = floor_from_offsets(offsets, ["a", "b", "c"])
    assert f.depth == pytest.approx(math.sqrt((1e-4 + 4e-6 + 1.6e-5) / 3))
    assert f.deg == pytest.approx(math.sqrt((0.09 + 0.01 + 0.04) / 3))
    g = f.without("a")
    assert g.names == ("b", "c") and g.depth == pytest.approx(math.sqrt((4e-6 + 1.6e-5) / 2))
    assert f.without("z").depth == f.depth  # a view not measured: the whole floor
    assert f.tuning() == {"map_floor_depth": f.depth, "map_floor_deg": f.deg}
    assert parse_map_floor(f.flag())["map_floor_depth"] == pytest.approx(f.depth, rel=1e-2)
    with pytest.raises(ValueError, match="at least one view"):
        floor_from_offsets(np.zeros((0, 2)), [])


def test_map_floor_flag_and_tuning_fields():
    assert parse_map_floor("0.6%,0.2deg") == {"map_floor_depth": pytest.approx(0.006), "map_floor_deg": 0.2}
    assert parse_map_floor(" 1.5 % , 0.01rad ")["map_floor_deg"] == pytest.approx(math.degrees(0.01))
    for bad in ("0.6,0.2deg", "0.6%", "x%,1deg", "0.6%,-1deg"):
        with pytest.raises(ValueError, match="--map-floor"):
            parse_map_floor(bad)
    cfg = hp.RefineConfig().replace(map_floor_depth=0.01, map_floor_deg=0.4)
    assert (cfg.tuning.map_floor_depth, cfg.tuning.map_floor_deg) == (0.01, 0.4)
    with pytest.raises(ValueError, match="map_floor_depth"):
        hp.Tuning(map_floor_depth=-0.1)
    with pytest.raises(ValueError, match="map_floor_deg"):
        hp.Tuning(map_floor_deg=float("nan"))
    # views whose minima are their poses to the last bit measure 0: the printed flag declares it, as Tuning does
    zero = floor_from_offsets(np.zeros((2, 2)), ["a", "b"])
    assert zero.flag() == "0%,0deg" and parse_map_floor(zero.flag()) == zero.tuning()
    assert hp.Tuning(**parse_map_floor(zero.flag())).map_floor_deg == 0.0
    with pytest.raises(ValueError, match="--max-rotation"):
        parse_angle("0deg")  # elsewhere an angle stays > 0


def test_student_quantile_and_the_cost_bound():
    """The t quantiles against a printed table, and the bound as its formula gives it: the 99.9 % one-sided
    prediction bound of a new log-cost from n known ones (n - 1 degrees of freedom)."""
    for dof, q in ((1, 318.309), (2, 22.327), (4, 7.173), (11, 4.025), (13, 3.852), (30, 3.385)):
        assert t_quantile(0.999, dof) == pytest.approx(q, abs=1e-3)
    assert t_quantile(0.975, 5) == pytest.approx(2.571, abs=1e-3)
    assert t_quantile(0.9, 3) == pytest.approx(1.638, abs=1e-3)
    costs = np.array([0.05, 0.06, 0.07, 0.055, 0.065])
    logs = np.log(costs)
    expected = math.exp(logs.mean() + 7.173182 * logs.std(ddof=1) * math.sqrt(1.2))
    assert cost_bound(costs) == pytest.approx(expected, rel=1e-6)
    assert cost_bound(costs[:2]) is None and cost_bound(np.array([0.05, np.nan, 0.0, 0.06])) is None
    with pytest.raises(ValueError, match="t_quantile"):
        t_quantile(0.4, 3)


def test_a_floor_with_costs_declares_its_bound():
    offsets = np.array([[0.01, 0.3], [0.002, 0.1], [0.004, 0.2], [0.003, 0.1]])
    costs = np.array([0.10, 0.12, 0.11, 0.50])
    f = floor_from_offsets(offsets, ["a", "b", "c", "d"], costs)
    assert f.cost_bound == pytest.approx(cost_bound(costs)) and f.flag().endswith("cs")
    declared = parse_map_floor(f.flag())
    assert declared["map_cost_bound"] == pytest.approx(f.cost_bound, rel=1e-2)
    assert set(declared) == set(f.tuning()) and hp.Tuning(**f.tuning()).map_cost_bound == f.cost_bound
    g = f.without("d")  # the outlying cost left out: a tighter bound, three views left
    assert list(g.costs) == [0.10, 0.12, 0.11] and g.cost_bound < f.cost_bound
    assert f.without("d").without("c").cost_bound is None and "cs" not in f.without("d").without("c").flag()
    with pytest.raises(ValueError, match="2 costs for 4 views"):
        floor_from_offsets(offsets, ["a", "b", "c", "d"], costs[:2])
    with pytest.raises(ValueError, match="map_cost_bound"):
        hp.Tuning(map_cost_bound=0.0)
    # unset, the bound stays out of the settings a report records (and a resume compares): older runs resume
    assert "map_cost_bound" not in hp.RefineConfig().to_dict()["tuning"]
    assert hp.RefineConfig().replace(**f.tuning()).to_dict()["tuning"]["map_cost_bound"] == f.cost_bound
    with pytest.raises(ValueError, match="cost bound"):
        parse_map_floor("0.6%,0.2deg,0cs")


def test_a_pose_above_the_maps_cost_level_is_refused():
    """The same query and prior: accepted without a bound or under a generous one, refused ("cost above the map's
    level", the prior returned) when the bound lies below the cost its pose ends at."""
    from hgsloc_plugin.cli.demo.queries import degrade

    scene, cam, poses = _room_views(1)
    img = degrade(hp.render(scene, cam, poses[0]), np.random.default_rng(0), occluder=False)  # a cost above 0
    prior = poses[0].perturbed_in_camera([0.0, 0.01, 0.0], [0.03, 0.0, 0.0])
    free = hp.HGSLocPlugin(scene).refine(img, cam, prior)
    assert free.accepted and free.search_cost > 0
    generous = hp.HGSLocPlugin(scene, hp.RefineConfig().replace(map_cost_bound=2.0 * free.search_cost))
    assert generous.refine(img, cam, prior).accepted
    tight = hp.HGSLocPlugin(scene, hp.RefineConfig().replace(map_cost_bound=0.5 * free.search_cost))
    r = tight.refine(img, cam, prior)
    assert not r.accepted and r.rejected == "cost above the map's level" and r.pose == prior


def _room_views(n=3):
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene

    return make_room_scene(0), hp.Camera.from_fov(160, 120, 60.0), query_poses(n, seed=1)


def test_a_map_that_made_its_views_has_a_floor_far_below_the_default():
    """Views rendered from the map itself: the map's minima lie at the poses (to the polish's precision), so the
    measured floor is a small fraction of the default (0.3 % of the depth / 0.1 deg), and declared it narrows the
    refined pose's sigma."""
    scene, cam, poses = _room_views()
    refiner = hp.HGSLocPlugin(scene)
    views = [(hp.render(scene, cam, p), cam, p, f"v{k}") for k, p in enumerate(poses)]
    f = map_floor(refiner, views)
    assert f.n == 3 and f.offsets.shape == (3, 2)
    assert f.depth < 0.0005 and f.deg < 0.02, (f.depth, f.deg)
    img, prior = views[0][0], poses[0].perturbed_in_camera([0.0, 0.01, 0.0], [0.03, 0.0, 0.0])
    default = refiner.refine(img, cam, prior)
    declared = hp.HGSLocPlugin(scene, hp.RefineConfig().replace(**f.tuning())).refine(img, cam, prior)
    assert default.accepted and declared.accepted
    assert declared.sigma_t < 0.5 * default.sigma_t and declared.sigma_r_deg < 0.5 * default.sigma_r_deg


def _cli(args, **kw):
    return subprocess.run([sys.executable, "-m", "hgsloc_plugin.cli", *args], capture_output=True, text=True,
                          timeout=600, cwd=ROOT, **kw)


def test_check_measures_the_floor_and_refine_declares_it(tmp_path):
    from hgsloc_plugin.evaluation.viz import save_png

    scene, cam, poses = _room_views(3)
    scene.to_ply(tmp_path / "room.ply")
    (tmp_path / "images").mkdir()
    lines = []
    for k, p in enumerate(poses):
        save_png(hp.render(scene, cam, p), tmp_path / "images" / f"v{k}.png")
        lines.append(f"v{k}.png " + " ".join(f"{x:.17g}" for x in (*p.qvec, *p.tvec)))
    (tmp_path / "gt.txt").write_text("\n".join(lines) + "\n")
    common = ["--scene", str(tmp_path / "room.ply"), "--poses", str(tmp_path / "gt.txt"), "--images",
              str(tmp_path / "images"), "--focal", str(cam.fx)]
    p = _cli(["check", *common, "--measure-floor", "--json"])
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout)
    floor = out["map_floor"]
    assert floor["views"] == 3 and set(floor["offsets"]) == set(floor["costs"]) == {"v0.png", "v1.png", "v2.png"}
    assert floor["depth"] < 0.0005 and floor["cost_bound"] > max(floor["costs"].values())
    assert floor["flag"].endswith("cs") and parse_map_floor(floor["flag"])["map_cost_bound"] > 0
    p = _cli(["refine", *common, "--out", str(tmp_path / "out.txt"), "--map-floor", floor["flag"], "--skip-check",
              "--quiet", "--json"])
    assert p.returncode == 0, p.stderr[-2000:]
    p = _cli(["refine", *common, "--out", str(tmp_path / "bad.txt"), "--map-floor", "0.5", "--json"])
    assert p.returncode != 0 and "--map-floor" in json.loads(p.stdout)["error"]
