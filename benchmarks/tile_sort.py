"""The CPU's serial tile sort alone: its time per pose against another checkout's, measured in the same run.

Usage: python -m benchmarks.tile_sort --before DIR [--cases snow_sharp room room_x20] [--rounds 3]
                                      [--repeats 30] [--out FILE]

Per case (the maps and first query of ``benchmarks/harness.py``; the densified room through its working set), at the
final scoring size, on poses about one pixel around the query's prior: the serial tile sort kernel
(``RasterConfig.sort="serial"``, ``kernels/tile_sort.py``) timed alone (its launches' seconds in
``kernels.launch.timed_launches`` while the renderer renders: on the CPU a launch runs its kernel), for one pose
(median of ``--repeats`` calls) and per pose of a 12-pose batch; then the same in the checkout ``DIR`` (the code
before a change: a ``git worktree`` with ``hgsloc_plugin/kernels`` and ``hgsloc_plugin/adapters`` linked to its
``kernels/`` and ``adapters/``, as ``startup.py --before`` needs; this script runs on both sides, each importing its
side's package, which the child reports and the parent checks). Each side runs in processes of its own, ``--rounds``
times, alternating; a row gives the median over the rounds, the speed-up (before / this checkout) and whether both
made the same tile lists (their starts and entries, bit for bit), and the share of the CPU time the hypervisor took
meanwhile (``benchmarks/machine.py``).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from benchmarks.machine import alternate, before_args, before_parser, run_child, write_before_table


def child(case: str, repeats: int) -> dict:
    """Times of the sort alone in the package this process imports (the ``--child`` side), and where that package
    lies (``checkout``)."""

    import hgsloc_plugin as hp
    from benchmarks import harness
    from hgsloc_plugin.evaluation.noise import se3_noise
    from hgsloc_plugin.kernels import launch
    from hgsloc_plugin.refine.plan import make_plan
    cam, scene, qs, bg = harness.load(case)
    prior = harness.case_priors(case, qs, 2.0, 1.0)[0]
    refiner = hp.HGSLocPlugin(scene, hp.RefineConfig(background=bg), raster=hp.RasterConfig(sort="serial"))
    plan = make_plan(refiner.config, scene, cam, prior, hp.QueryPrior())
    f = 0.5 * (plan.cam_final.fx + plan.cam_final.fy)
    poses = [se3_noise(prior, np.degrees(1.0 / f), plan.depth / f, np.random.default_rng(s)) for s in range(12)]
    renderer = refiner.renderer_for(plan)
    renderer.render_full(plan.cam_final, poses[:1], bg)
    renderer = getattr(renderer, "covering", lambda p: renderer)(poses)  # the working set's renderer
    if not hasattr(launch, "timed_launches"):
        raise SystemExit(f"{hp.__file__}: this checkout predates kernels.launch.timed_launches (2026-12-06), which "
                         "times the sort kernel here: compare with a later one")
    out = {"checkout": str(Path(hp.__file__).resolve().parents[1])}
    for label, batch in (("one", poses[:1]), ("batch", poses)):
        renderer.render_full(plan.cam_final, batch, bg)  # warm-up
        spent = []
        for _ in range(repeats):
            with launch.timed_launches() as launches:  # on the CPU a launch runs its kernel: the sort's own time
                renderer.render_full(plan.cam_final, batch, bg)
            spent.append(launches.by_kernel[SORT_KERNEL])
        out[label] = 1000 * float(np.median(spent)) / len(batch)
        ws = renderer.workspace(plan.cam_final, len(batch))  # the buffers the renders used
        starts = ws.tile_start.to_numpy()[:len(batch)]
        lists = renderer.pool.lists.isect.to_numpy()[:int(starts[:, -1].sum())]
        out[label + "_lists"] = hashlib.sha256(starts.tobytes() + lists.tobytes()).hexdigest()[:16]
        if label == "one":
            nt = renderer.pool.records.ntiles.to_numpy()[0, :renderer.n]
            out.update(gaussians=renderer.n, visible=int((nt > 0).sum()), entries=int(starts[0, -1]),
                       size=f"{plan.cam_final.width}x{plan.cam_final.height}")
    return out


#: the serial sort kernel's name (``kernels/tile_sort.py``), as ``LaunchTimes.by_kernel`` names it
SORT_KERNEL = "tile_sort"


def main() -> None:
    ap = before_parser(__doc__, ["snow_sharp", "room", "room_x20"])
    ap.add_argument("--repeats", type=int, default=30, help="timed sorts per process and batch")
    parsed = before_args(ap, lambda a: child(a.child, a.repeats))
    if parsed is None:
        return
    a, before = parsed

    rows = ["| case | Gaussians rendered | size | visible | entries | sort ms, one pose: before / now | per pose of "
            "12: before / now | speed-up: one / 12 | same lists | steal % |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for case in a.cases:
        args = [case, "--repeats", str(a.repeats)]
        got, steal = alternate(before, a.rounds, lambda path, args=args: run_child(__file__, path, args), case)
        med = {s: {k: float(np.median([r[k] for r in got[s]])) for k in ("one", "batch")} for s in got}
        r0 = got["now"][0]
        same = all(r[k] == r0[k] for s in got for r in got[s] for k in ("one_lists", "batch_lists"))
        rows.append(f"| {case} | {r0['gaussians']:,} | {r0['size']} | {r0['visible']:,} | {r0['entries']:,} | "
                    f"{med['before']['one']:.2f} / {med['now']['one']:.2f} | {med['before']['batch']:.2f} / "
                    f"{med['now']['batch']:.2f} | {med['before']['one'] / med['now']['one']:.2f}x / "
                    f"{med['before']['batch'] / med['now']['batch']:.2f}x | {'yes' if same else 'NO'} | "
                    f"{100 * steal:.0f} |")
        print(rows[-1], flush=True)
    if a.out:
        write_before_table(a.out, "Serial tile sort", "tile_sort.py",
                           f"Backend cpu; {a.rounds} processes per side and case, alternating; {a.repeats} timed "
                           "sorts each.", rows)


if __name__ == "__main__":
    main()
