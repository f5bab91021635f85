"""Tile lists by footprint: entries and times with the ellipse test against the whole box, in one run.

Usage: python -m benchmarks.tile_lists [--cases snow_sharp snow lego room room_x20] [--repeats 12] [--out FILE]

Per case (the maps and first query of ``benchmarks/throughput.py``; the densified room through its working set)
and per scoring size the default refinement uses: the tile-list entries of one render with ``RasterConfig.tile_test``
"ellipse" (each Gaussian binned into the tiles of its box its alpha ellipse reaches, ``kernels/footprint.py``) and
"box" (every tile of its box: the reference, the CPU's default); then, each the median of ``--repeats`` calls made in
turn on poses about one pixel around the true one, one plain render (ms), the windowed cost of a 12-pose batch (ms)
and one derivative pass (ms) with each, and the speed-ups (box / ellipse); and whether both give the same numbers
bit for bit (images, costs, derivatives).
"""

from __future__ import annotations

import numpy as np

import hgsloc_plugin as hp
from benchmarks.derivative_pass import compared_rows, median_ms, table_main
from hgsloc_plugin.core.image import resize_image
from hgsloc_plugin.render import read_rows

HEADER = ("| case | Gaussians rendered | size | entries: box / ellipse | render (ms): box / ellipse | "
          "12-pose cost (ms): box / ellipse | derivative pass (ms): box / ellipse | speed-up: render / cost / "
          "pass | same numbers |\n|---|---|---|---|---|---|---|---|---|")


def rows(case: str, repeats: int) -> list[str]:
    return compared_rows(case, repeats, (hp.RasterConfig(tile_test="box"), hp.RasterConfig(tile_test="ellipse")),
                         size_row)


def entries(r, cam: hp.Camera, pose, bg) -> int:
    """Tile-list entries of one render of ``pose``."""
    r.render_full(cam, [pose], bg)
    return int(read_rows(r.workspace(cam, 1).tile_start, 1)[0, -1])


def size_row(case: str, renderers, cam: hp.Camera, image: np.ndarray, poses: list, bg) -> str:
    """One Markdown row at ``cam``'s size, both ``renderers`` (box, ellipse) timed in turn on each of ``poses``."""
    box, ellipse = renderers
    img = resize_image(image, cam.width, cam.height)
    rs = {"box": box, "ellipse": ellipse}
    q = {k: r.upload_window_query(img) for k, r in rs.items()}
    batch = (poses * 12)[:12]
    outs = {k: [*r.render_full(cam, poses[:3], bg), r.window_cost(cam, batch, q[k], bg),
                *r.pose_gradient(cam, poses[:3], q[k], bg)] for k, r in rs.items()}
    same = all(np.array_equal(a, b) for a, b in zip(outs["box"], outs["ellipse"]))
    n = {k: entries(r, cam, poses[0], bg) for k, r in rs.items()}
    calls = {(k, op): fn for k, r in rs.items() for op, fn in (
        ("render", lambda p, r=r: r.render_full(cam, [p], bg)),
        ("cost", lambda p, r=r, k=k: r.window_cost(cam, batch, q[k], bg)),
        ("pass", lambda p, r=r, k=k: r.pose_gradient(cam, [p], q[k], bg)))}
    ms = median_ms(calls, poses)
    cols = " | ".join(f"{ms['box', op]:.1f} / {ms['ellipse', op]:.1f}" for op in ("render", "cost", "pass"))
    speed = " / ".join(f"{ms['box', op] / ms['ellipse', op]:.2f}x" for op in ("render", "cost", "pass"))
    row = (f"| {case} | {box.n:,} | {cam.width}x{cam.height} | {n['box']:,} / {n['ellipse']:,} | {cols} | "
           f"{speed} | {'yes' if same else 'NO'} |")
    print(row, flush=True)
    return row


def main() -> None:
    table_main(__doc__, "tile_lists.py", "Tile lists by footprint", HEADER, rows, 12)


if __name__ == "__main__":
    main()
