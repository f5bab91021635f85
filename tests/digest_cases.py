"""Frozen-behaviour cases: refinements on real photos (snow, both maps), lego and the demo room.

Each case refines a few queries from seeded priors and records every field of the results (poses, costs,
verdicts, render counts; wall time excluded). ``tests/test_digest.py`` compares a fresh run with the record in
``tests/data/digests.json``; after a deliberate change of behaviour, regenerate it with
``python -m tests.digest_cases --write``.

The last bits of the floats depend on the machine as well as the code: Taichi compiles the kernels for the host
CPU's vector extensions and numpy's BLAS picks its routines by them, and a borderline verdict can follow (the same
code gave different last digits, one flipped verdict and one pass less on an AVX-512 machine than on the one the
earlier record was made on). So the record holds one set of digests per machine signature (:func:`machine`),
each made from the same code, and the test compares with this machine's set (skipped where there is none).
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RECORD = Path(__file__).resolve().parent / "data" / "digests.json"
MACHINE_KEY = "_machine"  # a record of one machine only (before 2026-12-03): the entry naming it
#: CPU flags that change the arithmetic the kernels and numpy's BLAS are compiled or dispatched to
#: (avx512_vp2intersect: an EPYC generation whose kernels round otherwise under the same model name; across CPUs
#: the differences grow into other polish iterations and render counts: ``portable_difference`` checks what holds)
VECTOR_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl", "avx512_bf16",
                "avx512_vp2intersect", "neon", "asimd", "sve")


def machine() -> str:
    """The signature of what the float results depend on besides the code: architecture, CPU model, vector
    extensions, numpy and Taichi versions (e.g. ``x86_64 | AMD EPYC | avx,avx2,... | numpy 2.4.6 | taichi 1.7.4``)."""
    import taichi

    model, flags = platform.processor() or "?", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("?", platform.machine()):
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = set(value.split())
    except OSError:  # not Linux: the model and version parts only
        pass
    vector = ",".join(f for f in VECTOR_FLAGS if f in flags) or "?"
    return (f"{platform.machine()} | {model} | {vector} | numpy {np.__version__} | "
            f"taichi {'.'.join(map(str, taichi.__version__))}")


def _camera(d: Path):
    import hgsloc_plugin as hp

    cj = json.loads((d / "camera.json").read_text())
    return hp.Camera(int(cj["width"]), int(cj["height"]), cj["fx"], cj["fy"], cj["cx"], cj["cy"])


def _real_queries(name: str, limit: int):
    """(camera, [(image name, true pose, image [H, W, 3])]) of ``../shared/data/<name>`` (RGBA on white)."""
    import hgsloc_plugin as hp
    from hgsloc_plugin.core.image import load_image

    d = DATA / name
    out = []
    for line in (d / "gt.txt").read_text().splitlines()[:limit]:
        t = line.split()
        gt = hp.Pose([float(x) for x in t[1:5]], [float(x) for x in t[5:8]])
        out.append((t[0], gt, load_image(d / "queries" / t[0], background=(1.0, 1.0, 1.0) if name == "lego"
                                         else (0.0, 0.0, 0.0))))
    return _camera(d), out


def _priors(truths, rot_deg: float, shift_of_depth: float, seed: int, scene, cam):
    """Exact-magnitude priors: ``rot_deg`` degrees and ``shift_of_depth`` x the query's median depth."""
    from hgsloc_plugin.evaluation.noise import se3_noise
    from hgsloc_plugin.refine.plan import median_depth

    rng = np.random.default_rng(seed)
    return [se3_noise(g, rot_deg, shift_of_depth * median_depth(scene, cam, g), rng) for g in truths]


def _record(results) -> list[dict]:
    out = []
    for r in results:
        d = r.to_dict()
        d.pop("seconds")
        for p in d["polish"]:
            p.pop("seconds", None)
        out.append(d)
    return out


def _real(ply: str, folder: str, limit: int, rows, config=None, **per_query):
    import hgsloc_plugin as hp

    scene = hp.GaussianScene.from_ply(DATA / folder / ply)
    cam, qs = _real_queries(folder, limit)
    refiner = hp.HGSLocPlugin(scene, config)
    results = []
    for rot, frac, seed in rows:
        priors = _priors([g for _, g, _ in qs], rot, frac, seed, scene, cam)
        for (n, _, img), p in zip(qs, priors):
            results.append(refiner.refine(img, cam, p, name=n, **per_query))
    return results


def _room(config=None):
    import hgsloc_plugin as hp
    from hgsloc_plugin.cli.demo.queries import query_poses
    from hgsloc_plugin.cli.demo.scene import make_room_scene
    from hgsloc_plugin.evaluation.noise import se3_noise

    scene = make_room_scene(density=0.35)
    cam = hp.Camera(160, 120, 140.0, 140.0, 80.0, 60.0)
    refiner = hp.HGSLocPlugin(scene, config)
    rng = np.random.default_rng(7)
    results = []
    for k, (gt, kw) in enumerate(zip(query_poses(4, seed=3), (
            {}, {"prior_error": 0.03, "prior_error_deg": 1.0}, {"max_shift": 0.05}, {}))):
        img = hp.render(scene, cam, gt)
        prior = se3_noise(gt, 1.0 + 2.0 * (k == 3), 0.03 + 0.12 * (k == 3), rng)
        results.append(refiner.refine(img, cam, prior, name=f"room{k}", **kw))
    cost = hp.render_cost(scene, cam, query_poses(2, seed=3), hp.render(scene, cam, query_poses(1, seed=3)[0]),
                          metric="sad")
    return results, [float(c) for c in cost]


def _pose_file():
    """``refine_pose_file`` on three snow photos from an ACE-dialect file with inlier counts: the written pose
    file and the report (wall times excluded)."""
    import tempfile

    import hgsloc_plugin as hp
    from hgsloc_plugin.run.pipeline import refine_pose_file

    cam, qs = _real_queries("snow", 3)
    scene = hp.GaussianScene.from_ply(DATA / "snow" / "snow.ply")
    priors = _priors([g for _, g, _ in qs], 1.5, 0.03, 15, scene, cam)
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / "ace.txt", Path(tmp) / "refined.txt"
        src.write_text("".join(f"{n} {' '.join(repr(float(v)) for v in (*p.qvec, *p.tvec))} 1.0 0.02 {2600 + 400 * k}\n"
                               for k, ((n, _, _), p) in enumerate(zip(qs, priors))))
        rep = refine_pose_file(scene, src, DATA / "snow" / "queries", lambda n, w, h: cam, out, progress=False)
        text = out.read_text()
    for q in rep["queries"].values():
        q.pop("seconds", None)
        for p in q.get("polish", []):
            p.pop("seconds", None)
    for part in ("totals", "this_run"):
        for key in ("wall_seconds", "seconds_per_query", "query_seconds"):
            rep[part].pop(key)
    for k in ("input", "output", "scene"):  # paths of this checkout
        rep.pop(k)
    return [], [text, rep]


CASES = {
    # name: function returning a list of RefineResult (and optionally extra numbers)
    "snow": lambda: _real("snow.ply", "snow", 6, [(1.0, 0.02, 11), (4.0, 0.08, 12)]),
    "snow_sharp": lambda: _real("snow_sharp.ply", "snow", 6, [(1.0, 0.02, 13)], prior_error_depth=0.02,
                                prior_error_deg=1.0),
    "snow_search": lambda: _real("snow_sharp.ply", "snow", 3, [(4.0, 0.08, 16)], _config("search")),
    "lego": lambda: _real("lego.ply", "lego", 5, [(1.0, 0.01, 14)], _config("default", background=(1.0, 1.0, 1.0))),
    "room": _room,
    "room_working_set": lambda: _room(_config("search", working_set_min=0, coarse_lod_pixels=2.0)),
    "pose_file": _pose_file,
}


def _config(preset: str, **kw):
    from hgsloc_plugin.refine import RefineConfig

    return RefineConfig.preset(preset, **kw)


def run_case(name: str) -> dict:
    """The record of one case: its results' fields (JSON-ready), extra numbers and a digest of both."""
    out = CASES[name]()
    results, extra = out if isinstance(out, tuple) else (out, [])
    rec = {"results": _record(results), "extra": extra}
    blob = json.dumps(rec, sort_keys=True, default=repr).encode()
    rec["digest"] = hashlib.sha256(blob).hexdigest()[:16]
    return rec


#: on a machine without a record of its own: each refinement's verdict must equal the records' and its pose lie
#: within these of theirs (rotation in degrees; translation x max(1, |t|) in scene units). Between the three
#: recorded CPUs (2026-12-06) the poses differ by up to 0.013 deg and 1.1e-3 units (lego, |t| ~ 4), the verdicts
#: never (one route differs: the gradient route's pose accepted on one CPU, the search's on another, 1.5e-5 apart)
PORTABLE_DEG, PORTABLE_T = 0.05, 1e-3


def _poses(rec: dict) -> list[tuple[str, bool, str | None, np.ndarray, np.ndarray]]:
    """(name, accepted, rejected, qvec, tvec) of each refinement a case record holds (its results, or for the
    pose-file case the written file's lines and its report's verdicts)."""
    if rec["results"]:
        return [(r["name"], r["accepted"], r["rejected"], np.array(r["qvec"]), np.array(r["tvec"]))
                for r in rec["results"]]
    text, report = rec["extra"]
    out = []
    for line in text.splitlines():
        t = line.split()
        q = report["queries"][t[0]]
        out.append((t[0], q["accepted"], q.get("rejected"), np.array(t[1:5], float), np.array(t[5:8], float)))
    return out


def portable_difference(got: dict, record: dict) -> str | None:
    """Where ``got`` and another machine's ``record`` of one case differ beyond float rounding (None: they agree):
    a verdict (accepted, rejected), or a pose beyond ``PORTABLE_DEG`` / ``PORTABLE_T``."""
    from hgsloc_plugin.core.pose import qvec_to_rotmat, rotation_angle_deg

    a, b = _poses(got), _poses(record)
    if [x[0] for x in a] != [y[0] for y in b]:
        return f"queries {[x[0] for x in a]}, recorded {[y[0] for y in b]}"
    for (name, acc, rej, q, t), (_, acc_r, rej_r, q_r, t_r) in zip(a, b):
        if (acc, rej) != (acc_r, rej_r):
            return f"{name}: accepted {acc} ({rej}), recorded {acc_r} ({rej_r})"
        angle = rotation_angle_deg(qvec_to_rotmat(q), qvec_to_rotmat(q_r))
        shift = float(np.linalg.norm(t - t_r))
        if angle > PORTABLE_DEG or shift > PORTABLE_T * max(1.0, float(np.linalg.norm(t_r))):
            return f"{name}: pose {shift:.2e} units / {angle:.2e} deg from the record's"
    return None


def load_records() -> dict[str, dict]:
    """The record: {machine signature: {case name: its record}} (an older one-machine record read as such)."""
    record = json.loads(RECORD.read_text()) if RECORD.exists() else {}
    if MACHINE_KEY in record:
        here = record.pop(MACHINE_KEY)
        return {here: record}
    return record


def main(argv: list[str]) -> int:
    names = [a for a in argv if not a.startswith("--")] or list(CASES)
    records = load_records()
    here = machine()
    if here not in records:
        print(f"no record for this machine ({here}; recorded: {sorted(records)})", file=sys.stderr)
        if "--write" in argv and set(names) != set(CASES):
            print("write every case on a new machine (no case names)", file=sys.stderr)
            return 2
    if "--write" in argv and "--all-machines" not in argv and set(records) - {here}:
        print(f"the other machines' digests stay as they are ({sorted(set(records) - {here})}): after a deliberate "
              "change of behaviour, pass --all-machines (they no longer hold) and record each machine again",
              file=sys.stderr)
    if "--all-machines" in argv:  # a change of behaviour: the other machines' digests no longer hold
        records = {k: v for k, v in records.items() if k == here}
    record = records.setdefault(here, {})
    changed = 0
    for name in names:
        rec = run_case(name)
        same = record.get(name, {}).get("digest") == rec["digest"]
        changed += not same
        print(f"{name}: {rec['digest']} ({'same as the record' if same else 'differs from the record'})")
        record[name] = rec
    if "--write" in argv:
        RECORD.write_text(json.dumps(records, indent=1, sort_keys=True, default=repr) + "\n")
    return 1 if changed and "--write" not in argv else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
