"""Pose-file dialects on the real 7-Scenes files, name matching, intrinsics, and the evaluator anchors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hgsloc_plugin import Pose
from hgsloc_plugin.adapters import canonical_name, match_names, read_poses, resolve_image, write_poses
from hgsloc_plugin.adapters.intrinsics import from_pgt, from_query_list, parse_query_list
from hgsloc_plugin.evaluation.evaluate import evaluate, mean_over_scenes

from .conftest import shared_path

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"]
FILES = ["ace.txt", "glace.txt", "marepo.txt", "dfnet.txt", "hloc.txt", "pgt_sfm_test.txt"]


@pytest.mark.parametrize("scene", SCENES)
def test_every_real_file_reads_and_writes_back_byte_identical(tmp_path, scene):
    root = shared_path("poses", "7scenes", scene)
    counts = set()
    for f in FILES:
        pf = read_poses(root / f)
        counts.add(len(pf))
        assert all(p is not None for p in pf.values())
        out = write_poses(tmp_path / f, dict(pf), like=pf)
        assert out.read_bytes() == (root / f).read_bytes(), f
    assert len(counts) == 1
    assert read_poses(root / "ace.txt").dialect == "ace" and read_poses(root / "pgt_sfm_test.txt").dialect == "pgt"


def test_changed_pose_keeps_columns_and_order(tmp_path):
    src = shared_path("poses", "7scenes", "heads", "ace.txt")
    pf = read_poses(src)
    name = list(pf)[5]
    new = Pose([1, 0, 0, 0], [0.5, -0.25, 2.0])
    out = write_poses(tmp_path / "o.txt", {name: new}, like=pf)
    a, b = src.read_text().splitlines(), out.read_text().splitlines()
    assert len(a) == len(b)
    diff = [i for i in range(len(a)) if a[i] != b[i]]
    assert diff == [5]
    tok_a, tok_b = a[5].split(), b[5].split()
    assert tok_b[0] == tok_a[0] and tok_b[8:] == tok_a[8:] and len(tok_b) == 11
    back = read_poses(out)[name]
    assert back == new


def test_evaluator_reproduces_published_anchors():
    res = {}
    for loc in ("ace", "marepo"):
        per = [evaluate(read_poses(shared_path("poses", "7scenes", s, f"{loc}.txt")),
                        read_poses(shared_path("poses", "7scenes", s, "pgt_sfm_test.txt"))) for s in SCENES]
        res[loc] = mean_over_scenes(per)
    ace, mar = res["ace"], res["marepo"]
    assert round(ace["median_translation_cm"], 2) == 1.09 and round(ace["median_rotation_deg"], 2) == 0.34
    assert [round(100 * ace["recall"][k], 1) for k in ("5cm5deg", "2cm2deg", "1cm1deg")] == [97.3, 83.3, 56.3]
    assert round(mar["median_translation_cm"], 2) == 2.92 and round(100 * mar["recall"]["1cm1deg"], 1) == 6.2


def test_evaluator_matches_hand_computation():
    scene = "heads"
    est = read_poses(shared_path("poses", "7scenes", scene, "ace.txt"))
    gt = read_poses(shared_path("poses", "7scenes", scene, "pgt_sfm_test.txt"))
    t, r = [], []
    est_by = {n.replace("/", "-"): p for n, p in est.items()}
    for n, g in gt.items():
        e = est_by[n.replace("/", "-")]
        t.append(np.linalg.norm(e.centre() - g.centre()))
        cos = (np.trace(g.R.T @ e.R) - 1) / 2
        r.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    t, r = np.array(t), np.array(r)
    ev = evaluate(est, gt)
    assert ev["median_translation_cm"] == pytest.approx(np.median(t) * 100, rel=1e-9)
    assert ev["median_rotation_deg"] == pytest.approx(np.median(r), abs=1e-4)
    assert ev["recall"]["2cm2deg"] == pytest.approx(np.mean((t < 0.02) & (r < 2)))
    # ACE's own error columns agree with ours
    cols = np.array([[float(x) for x in est.record(n).tokens[8:10]] for n in est])
    assert np.median(cols[:, 1]) * 100 == pytest.approx(ev["median_translation_cm"], abs=1e-3)


def test_missing_queries_are_not_scored_unless_asked():
    """A ground truth of more images than the estimates (a full gt.txt, a subset refined): the shared ones are
    scored; with ``missing_as_failure`` (a benchmark's protocol) the others count as failures."""
    gt = {f"seq-01/frame-{i:06d}.color.png": Pose.identity() for i in range(4)}
    est = {"seq-01-frame-000000.color.png": Pose.identity(), "seq-01-frame-000001.color.png": Pose.identity()}
    shared = evaluate(est, gt)
    assert shared["n"] == 2 and shared["missing"] == 2 and shared["recall"]["1cm1deg"] == 1.0
    assert shared["median_translation_cm"] == 0.0 and "seq-01/frame-000003.color.png" not in shared["errors"]
    ev = evaluate(est, gt, missing_as_failure=True)
    assert ev["missing"] == 2 and ev["recall"]["1cm1deg"] == 0.5
    assert ev["errors"]["seq-01/frame-000003.color.png"] == [float("inf"), 180.0]
    assert ev["median_translation_cm"] == float("inf")  # median of [0, 0, inf, inf] (numpy: mean of the middle two)


def test_name_styles_match_every_query():
    for scene in SCENES:
        hloc = read_poses(shared_path("poses", "7scenes", scene, "hloc.txt"))
        ace = read_poses(shared_path("poses", "7scenes", scene, "ace.txt"))
        m = match_names(list(hloc), list(ace))
        assert len(m) == len(hloc) == len(ace)
    assert canonical_name("seq2/frame00001.png") == canonical_name("seq2_frame00001.png")
    assert canonical_name("data/frame-000178.color.jpg") == canonical_name("frame-000178.color.jpg")


def test_resolve_image_across_styles(tmp_path):
    (tmp_path / "seq-01").mkdir()
    f = tmp_path / "seq-01" / "frame-000003.color.png"
    f.write_bytes(b"x")
    assert resolve_image("seq-01-frame-000003.color.png", tmp_path) == f
    assert resolve_image("seq-01/frame-000003.color.png", tmp_path) == f
    with pytest.raises(FileNotFoundError, match="frame-000004"):
        resolve_image("seq-01-frame-000004.color.png", tmp_path)


def test_raw_marepo_output_is_read_per_the_robust_rule(tmp_path):
    """The shape test_marepo.py writes: each record followed by the batch's error tensors, wrapped."""
    p = tmp_path / "poses_marepo.txt"
    text = ("seq-01-frame-000000.color.png 0.9987 0.0123 -0.0456 0.0078 0.1 0.2 0.3 tensor([1.2345, 0.5432, "
            "2.3456, 0.8765, 1.1111, 0.2222,\n"
            "        0.3333, 0.4444]) tensor([0.0123, 0.0456, 0.0789, 0.0012, 0.0345, 0.0678,\n"
            "        0.0901, 0.0234])\n"
            "seq-01-frame-000001.color.png 0.9 0.1 0 0 0.1 0.2 0.3 tensor([0.1, 0.2]) tensor([0.01, 0.02])\n"
            "seq-01-frame-000002.color.png 1 0 0 0 1.5 -2e-05 3\n")
    p.write_text(text)
    pf = read_poses(p)
    assert pf.dialect == "marepo"
    assert list(pf) == ["seq-01-frame-000000.color.png", "seq-01-frame-000001.color.png",
                        "seq-01-frame-000002.color.png"]
    np.testing.assert_allclose(pf["seq-01-frame-000000.color.png"].tvec, [0.1, 0.2, 0.3])
    assert pf["seq-01-frame-000002.color.png"].tvec[1] == -2e-05
    assert write_poses(tmp_path / "o.txt", dict(pf), like=pf).read_bytes() == p.read_bytes()
    moved = write_poses(tmp_path / "o2.txt", {"seq-01-frame-000001.color.png": Pose.identity()}, like=pf)
    back = read_poses(moved)
    assert back["seq-01-frame-000001.color.png"] == Pose.identity() and len(back) == 3
    assert moved.read_text().splitlines()[1:3] == text.splitlines()[1:3]  # wrapped lines kept verbatim


def test_raw_marepo_lines_that_are_neither_records_nor_tensors(tmp_path, caplog):
    """A truncated record is a lost query: an error naming its line, in raw Marepo output and in an hloc-shaped
    file alike; so is a stray line that is no printed tensor (in any dialect: it neither switches the file to
    Marepo nor is copied into the output); a record with a non-finite value is a failed estimate, one warning."""
    raw = ("a.png 1 0 0 0 0 0 0 tensor([0.1, nan,\n"
           "        inf, 0.2], device='cuda:0') tensor([1.0e-02, 2.0e-02], dtype=torch.float64)\n")
    p = tmp_path / "raw.txt"
    p.write_text(raw + "b.png 1 0 0 0 nan 0 0 tensor([0.1])\n")
    with caplog.at_level("WARNING", logger="hgsloc_plugin"):
        pf = read_poses(p)
    assert pf.dialect == "marepo" and list(pf) == ["a.png", "b.png"] and pf["b.png"] is None
    assert [r.getMessage() for r in caplog.records if "raw.txt:3" in r.getMessage()]  # the failed estimate
    assert not [r for r in caplog.records if "printed tensor" in r.getMessage()]  # tensors are not strays
    for text, line in ((raw + "b.png 1 0 0\n", 3), ("a.png 1 0 0 0 0 0 0\nb.png 1 0 0 0 0\n", 2),
                       ("a.png 1 0 0 0 0 0 0 tensor([1])\nb.png 1 0 0 0 x 0 0 tensor([1])\n", 2)):
        p.write_text(text)
        with pytest.raises(ValueError, match=rf"raw.txt:{line}: damaged pose record for b.png"):
            read_poses(p)
    for text, line in (("a.png 1 0 0 0 0 0 0\ngarbage line here\nb.png 1 0 0 0 1 1 1\n", 2),
                       (raw + "lorem ipsum dolor\n", 3),
                       ("a.png 1 0 0 0 0 0 0 1 1 9\nlorem ipsum dolor\n", 2)):
        p.write_text(text)
        with pytest.raises(ValueError, match=rf"raw.txt:{line}: neither a pose record nor a printed tensor"):
            read_poses(p)
    p.write_text("".join(f"{c}.png 1 0 0 0 nan 0 0\n" for c in "abc"))
    caplog.clear()
    with caplog.at_level("WARNING", logger="hgsloc_plugin"):
        pf = read_poses(p)
    assert [pf[c + ".png"] for c in "abc"] == [None] * 3
    assert len(caplog.records) == 1 and "3 unusable poses" in caplog.records[0].getMessage()


def test_crlf_file_stays_crlf(tmp_path):
    p = tmp_path / "crlf.txt"
    p.write_bytes(b"a.png 1 0 0 0 0 0 0\r\n# note\r\nb.png 1 0 0 0 1 1 1\r\n")
    pf = read_poses(p)
    assert write_poses(tmp_path / "same.txt", dict(pf), like=pf).read_bytes() == p.read_bytes()
    moved = write_poses(tmp_path / "o.txt", {"a.png": Pose([1, 0, 0, 0], [0.5, 0, 0])}, like=pf).read_bytes()
    assert moved.count(b"\r\n") == 3 and moved.count(b"\n") == 3
    assert read_poses(tmp_path / "o.txt")["a.png"] == Pose([1, 0, 0, 0], [0.5, 0, 0])


def test_byte_order_mark_is_no_part_of_a_name(tmp_path):
    """A file saved by a Windows editor starts with a UTF-8 BOM: the first image is still found, and the BOM is
    written back (the file is otherwise byte for byte)."""
    p = tmp_path / "bom.txt"
    p.write_bytes("\ufeffa.png 1 0 0 0 0 0 0\r\nb.png 1 0 0 0 1 1 1\r\n".encode())
    pf = read_poses(p)
    assert list(pf) == ["a.png", "b.png"] and pf.dialect == "hloc"
    assert write_poses(tmp_path / "same.txt", dict(pf), like=pf).read_bytes() == p.read_bytes()
    T = Pose([1, 0, 0, 0], [0.5, 0, 0])
    moved = write_poses(tmp_path / "o.txt", {"a.png": T}, like=pf).read_bytes()
    assert moved.startswith("\ufeffa.png 1.0 0.0".encode()) and read_poses(tmp_path / "o.txt")["a.png"] == T
    q = tmp_path / "queries_with_intrinsics.txt"
    q.write_bytes("\ufeffa.png SIMPLE_PINHOLE 640 480 525 320 240\n".encode())
    assert from_query_list(q)("a.png", 640, 480).fx == 525
    cams = tmp_path / "cameras.json"
    cams.write_bytes(("\ufeff" + json.dumps([{"id": 0, "img_name": "a", "width": 10, "height": 8, "fx": 5, "fy": 5,
                                                "position": [0, 0, 1], "rotation": np.eye(3).tolist()}])).encode())
    assert len(read_poses(cams)) == 1


def test_marepo_tensor_lines_are_kept_and_other_lines_refused(tmp_path):
    p2 = tmp_path / "clean.txt"
    p2.write_text("a.png 1 0 0 0 0 0 0\n 0.1, 0.2]) tensor([3.0e-01,\nb.png 1 0 0 0 1 1 1\n")
    pf2 = read_poses(p2)
    assert pf2.dialect == "marepo" and list(pf2) == ["a.png", "b.png"]
    assert write_poses(tmp_path / "o.txt", dict(pf2), like=pf2).read_bytes() == p2.read_bytes()
    p2.write_text("a.png 1 0 0 0 0 0 0\nwrapped 0.1 0.2\nb.png 1 0 0 0 1 1 1\n")
    with pytest.raises(ValueError, match="clean.txt:2: neither a pose record nor a printed tensor: 'wrapped"):
        read_poses(p2)


def test_unusable_estimate_lines_are_named(tmp_path, caplog):
    p = tmp_path / "est.txt"
    p.write_text("a.png 1 0 0 0 0 0 0\nb.png nan 0 0 0 0 0 0\nc.png 0 0 0 0 1 2 3\n")
    with caplog.at_level("WARNING", logger="hgsloc_plugin"):
        pf = read_poses(p)
    assert pf["b.png"] is None and pf["c.png"] is None
    msgs = [r.getMessage() for r in caplog.records]  # one warning per cause, naming the first line
    assert len(msgs) == 1 and "est.txt:2" in msgs[0] and "2 unusable poses" in msgs[0] and "b.png" in msgs[0], msgs


@pytest.mark.parametrize("text,match", [
    ("a.png 1 0 0 0 0 0\n", "columns|dialect|no pose"),
    ("a.png 1 0 0 0 0 0 0 1 2\nb.png 1 0 0 0 0 0 0 1 2\n", "columns|dialect|widths"),
    ("a.png 1 0 0 0 0 0 x 1 2 3\n", "not a number|dialect"),
    ("a.png 1 0 0 0 0 0 0\na.png 1 0 0 0 0 0 0\n", "twice"),
])
def test_malformed_files_name_file_and_line(tmp_path, text, match):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(ValueError, match=match) as ei:
        read_poses(p)
    assert "bad.txt" in str(ei.value)


def test_malformed_line_in_known_dialect_names_line(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("a.png 1 0 0 0 0 0 0 1 2 3\nb.png 1 0 0 0 0 0 0 1 2\n")
    with pytest.raises(ValueError, match=r"bad.txt:2: expected 11 columns"):
        read_poses(p, "ace")


def test_ace_nan_prior_is_kept_as_failed(tmp_path):
    p = tmp_path / "ace.txt"
    p.write_text("a.png nan nan nan nan 0 0 0 1 2 3\nb.png 1 0 0 0 0 0 0 1 2 3\n")
    pf = read_poses(p, "ace")
    assert pf["a.png"] is None and pf["b.png"] == Pose.identity()
    assert write_poses(tmp_path / "o.txt", dict(pf), like=pf).read_bytes() == p.read_bytes()


def test_refuses_to_overwrite_input(tmp_path):
    p = tmp_path / "in.txt"
    p.write_text("a.png 1 0 0 0 0 0 0\n")
    pf = read_poses(p)
    with pytest.raises(ValueError, match="overwrite"):
        write_poses(p, {"a.png": Pose([1, 0, 0, 0], [1, 0, 0])}, like=pf)
    assert p.read_text() == "a.png 1 0 0 0 0 0 0\n"


def test_intrinsics_sources(tmp_path):
    f = from_pgt(shared_path("poses", "7scenes", "chess", "pgt_sfm_test.txt"))
    cam = f("seq-03-frame-000000.color.png", 640, 480)
    assert cam.fx == 526.22 and cam.cx == 320 and cam.cy == 240
    q = tmp_path / "queries_with_intrinsics.txt"
    q.write_text("# comment\nseq-01/frame-000000.color.png SIMPLE_PINHOLE 640 480 525 320 240\n"
                 "seq-01/frame-000001.color.png PINHOLE 640 480 520 521 319 241\n\n")
    fn = from_query_list(q)
    c = fn("seq-01-frame-000001.color.png", 320, 240)
    assert (c.width, c.fx, c.fy, c.cx) == (320, 260.0, 260.5, 159.5)
    # distortion is carried, zero distortion (how hloc writes a pinhole-like camera) is a pinhole camera
    q.write_text("x.png SIMPLE_RADIAL 640 480 525 320 240 0.1\ny.png SIMPLE_RADIAL 640 480 525 320 240 0.0\n")
    cams = parse_query_list(q)
    assert cams["x"].distortion.coeffs == (0.1,) and cams["y"].distortion is None
    # a pose file given as a query list is named as such, with its line (not Python's "invalid literal for int()")
    q.write_text("x.png 1.0 0 0 0 0.1 0.2 0.3\n")
    with pytest.raises(ValueError, match=r"queries_with_intrinsics.txt:1: '1.0' is not a COLMAP camera model.*pose"):
        parse_query_list(q)
    q.write_text("x.png SIMPLE_PINHOLE 640 480 525 320 240\ny.png SIMPLE_PINHOLE 640 480 525 320\n")
    with pytest.raises(ValueError, match=r"queries_with_intrinsics.txt:2: camera model SIMPLE_PINHOLE takes 3"):
        parse_query_list(q)


def test_cambridge_dialect_centre_and_round_trip(tmp_path):
    from hgsloc_plugin.core.pose import so3_exp

    R = so3_exp([0.1, -0.2, 0.3])
    c = np.array([10.0, -5.0, 2.0])
    T = Pose.from_centre(R, c)
    q = " ".join(repr(float(v)) for v in T.qvec)
    p = tmp_path / "dataset_test.txt"
    text = (f"Visual Landmark Dataset V1\nImageFile, Camera Position [X Y Z W P Q R]\n\n"
            f"seq2/frame00001.png 10.0 -5.0 2.0 {q}\nseq2/frame00002.png 1 2 3 1 0 0 0\n")
    p.write_text(text)
    pf = read_poses(p)
    assert pf.dialect == "cambridge" and list(pf) == ["seq2/frame00001.png", "seq2/frame00002.png"]
    np.testing.assert_allclose(pf["seq2/frame00001.png"].centre(), c, atol=1e-9)
    np.testing.assert_allclose(pf["seq2/frame00001.png"].R, R, atol=1e-12)
    assert write_poses(tmp_path / "o.txt", dict(pf), like=pf).read_text() == text
    new = Pose.from_centre(R, c + 1)
    out = write_poses(tmp_path / "o2.txt", {"seq2/frame00001.png": new}, like=pf)
    back = read_poses(out)
    np.testing.assert_allclose(back["seq2/frame00001.png"].centre(), c + 1, atol=1e-9)
    assert out.read_text().splitlines()[:3] == text.splitlines()[:3]
    assert canonical_name("seq2_frame00001.png") in {canonical_name(n) for n in pf}
