"""Tile binning and depth ordering, in Taichi (CONVENTIONS §6 step 6).

Per pose: gather the visible Gaussians as 64-bit keys ``depth bits << 32 | index``, sort them with a stable LSD
radix sort (3 passes) on the depth bits (depths are positive, so the bit pattern orders like the value), then a
stable counting sort by tile id (count, prefix sum, scatter). Each tile's list therefore ends up in depth order,
ties in index order, the same key order as gsplat's (tile | depth) sort. Each Gaussian's tile box travels through
the radix passes packed in one word beside its key, so the tile passes read it in order instead of gathering it
by id; the digit counts of all passes are taken while gathering, in a local array. A Gaussian goes into the tiles
of its footprint only (``footprint.py``: its box, or the box's tiles its ellipse meets).
Poses are processed in parallel, each pose serially;
this suits the CPU backend (``RasterConfig.sort="serial"``; its 24 KB of digit counts per pose sit in the cache
there, in slow local memory on a GPU). Reference twin: ``tests/reference/render_torch.py::bin_tiles``.

On a GPU one thread per pose is the slowest way to sort (a whole pose's radix passes on one thread).
There (``sort="parallel"``) each visible Gaussian writes one 64-bit key per tile it touches, in parallel,
``(pose * tiles + tile) << 32 | depth bits``, at its exclusive prefix sum of the tile counts
(:func:`write_keys`); the keys are sorted by a stable LSD radix sort written as Taichi kernels
(``radix.py``) and each tile's range is its key count (:func:`bin_parallel`). Keys are written in Gaussian order,
so the stable sort leaves ties in index order: the lists are those of the serial sort, entry for entry.
"""


import functools

import numpy as np
import taichi as ti

from .config import RasterConfig
from .footprint import in_footprint, read_mask
from .grain import item, spread
from .launch import launcher
from .radix import block_size, blocks, passes, scan_rows, sort_passes

RADIX_BITS = 11  # digit width of the depth sort's passes (the third pass takes the remaining 10 bits)
RADIX_PASSES = 3  # 33 bits: a positive float's 31
RADIX = 1 << RADIX_BITS  # histogram buckets per pass
RADIX_MASK = RADIX - 1


@ti.func
def count_tiles(ntiles: ti.template(), num_poses, num_gaussians, totals: ti.template()):
    """Per-pose intersection totals: ntiles [B, >= N] -> totals [B] int64 (the first ``num_gaussians`` entries; a
    pooled workspace may be longer). One task per pose on the CPU (grain.py)."""
    stride = ti.static(spread())
    for task in range(num_poses * stride):
        is_item, b, _ = item(task, stride, 1)
        if is_item:
            s = ti.i64(0)
            for i in range(num_gaussians):
                s += ntiles[b, i]
            totals[b] = s


@ti.func
def pack_box(rect: ti.template(), b, i):
    """The tile box of ``rect[b, i]`` (x0, y0, x1, y1, each < 2^15) packed in one word: x0, x1, y0, y1 in 16 bits
    each, low to high (``tile_sort``'s ``boxes``)."""
    return (ti.cast(rect[b, i, 0], ti.u64) | (ti.cast(rect[b, i, 2], ti.u64) << ti.u64(16))
            | (ti.cast(rect[b, i, 1], ti.u64) << ti.u64(32)) | (ti.cast(rect[b, i, 3], ti.u64) << ti.u64(48)))


@ti.func
def key_id(v):
    """The Gaussian index in the low word of a serial-sort key ``depth bits << 32 | index``."""
    return ti.cast(v & ti.u64(0xFFFFFFFF), ti.i32)


@ti.func
def unpack_box(v):
    """(x0, x1, y0, y1) of a tile box packed by :func:`pack_box`."""
    return (ti.cast(v & ti.u64(0xFFFF), ti.i32), ti.cast((v >> ti.u64(16)) & ti.u64(0xFFFF), ti.i32),
            ti.cast((v >> ti.u64(32)) & ti.u64(0xFFFF), ti.i32), ti.cast(v >> ti.u64(48), ti.i32))


@functools.cache
def tile_sort_kernel(config: RasterConfig, ellipse: bool):
    """Compiled sorting kernel; ``ellipse``: each Gaussian into the tiles of its footprint mask (``footprint.py``,
    the projection's ``ellipse_tiles``), else every tile of its box.

    Kernel arguments:
        depth [B, >= N], rect [B, >= N, footprint.RECT_SIZE], ntiles [B, >= N], isect_base [B] (start of each
        pose in ``isect``),
        tiles_x, tiles_y, num_poses, num_gaussians N (a pooled workspace may hold more columns);
        scratch: keys [2, B, N] u64 (``depth bits << 32 | Gaussian id``, ping-pong), boxes [2, B, N] u64 (the
        tile box beside each key), cursor [B, T] i32;
        outputs: tile_start [B, T + 1] (offsets relative to isect_base[b]), isect [M] Gaussian ids.
    """

    @ti.kernel
    def tile_sort(
        depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
        rect: ti.types.ndarray(dtype=ti.i32, ndim=3),
        ntiles: ti.types.ndarray(dtype=ti.i32, ndim=2),
        isect_base: ti.types.ndarray(dtype=ti.i64, ndim=1),
        tiles_x: ti.i32,
        tiles_y: ti.i32,
        num_poses: ti.i32,
        num_gaussians: ti.i32,
        keys: ti.types.ndarray(dtype=ti.u64, ndim=3),
        boxes: ti.types.ndarray(dtype=ti.u64, ndim=3),
        cursor: ti.types.ndarray(dtype=ti.i32, ndim=2),
        tile_start: ti.types.ndarray(dtype=ti.i32, ndim=2),
        isect: ti.types.ndarray(dtype=ti.i32, ndim=1),
    ):
        n = num_gaussians
        num_tiles = tiles_x * tiles_y
        stride = ti.static(spread())  # one task per pose on the CPU (grain.py)
        for task in range(num_poses * stride):
            is_item, b, _ = item(task, stride, 1)
            if is_item:
                # gather the visible Gaussians with the digit counts of every pass (local: a histogram in a device
                # buffer cost 2-3x, its every update a load of the buffer's address)
                hist = ti.Vector([0] * (RADIX_PASSES * RADIX), ti.i32)
                m = 0
                for i in range(n):
                    if ntiles[b, i] > 0:
                        key = ti.bit_cast(depth[b, i], ti.u32)
                        keys[0, b, m] = (ti.cast(key, ti.u64) << ti.u64(32)) | ti.cast(i, ti.u64)
                        boxes[0, b, m] = pack_box(rect, b, i)
                        for p in ti.static(range(RADIX_PASSES)):
                            hist[p * RADIX + ti.cast((key >> (RADIX_BITS * p)) & RADIX_MASK, ti.i32)] += 1
                        m += 1
                # stable LSD radix sort on the depth bits, 3 passes of 11, 11 and 10 bits (the 2048-bucket
                # histogram fits the L1 cache): 0 -> 1 -> 0 -> 1, the sorted run ends in 1
                for p in ti.static(range(RADIX_PASSES)):
                    shift = ti.static(32 + RADIX_BITS * p)
                    src = ti.static(p % 2)
                    acc = 0
                    for k in range(p * RADIX, (p + 1) * RADIX):
                        c = hist[k]
                        hist[k] = acc
                        acc += c
                    for j in range(m):
                        v = keys[src, b, j]
                        digit = ti.cast((v >> shift) & RADIX_MASK, ti.i32) + p * RADIX
                        pos = hist[digit]
                        hist[digit] = pos + 1
                        keys[1 - src, b, pos] = v
                        boxes[1 - src, b, pos] = boxes[src, b, j]
                # stable counting sort by tile id, visiting Gaussians in depth order
                for t in range(num_tiles):
                    cursor[b, t] = 0
                for j in range(m):
                    x0, x1, y0, y1 = unpack_box(boxes[1, b, j])
                    mask = read_mask(rect, b, key_id(keys[1, b, j]), ellipse)
                    k = 0
                    for ty in range(y0, y1):
                        for tx in range(x0, x1):
                            if in_footprint(mask, k, ellipse):
                                cursor[b, ty * tiles_x + tx] += 1
                            k += 1
                acc2 = 0
                for t in range(num_tiles):
                    c = cursor[b, t]
                    tile_start[b, t] = acc2
                    cursor[b, t] = acc2
                    acc2 += c
                tile_start[b, num_tiles] = acc2
                base = ti.cast(isect_base[b], ti.i32)
                for j in range(m):
                    g = key_id(keys[1, b, j])
                    x0, x1, y0, y1 = unpack_box(boxes[1, b, j])
                    mask = read_mask(rect, b, g, ellipse)
                    k = 0
                    for ty in range(y0, y1):
                        for tx in range(x0, x1):
                            if in_footprint(mask, k, ellipse):
                                t = ty * tiles_x + tx
                                isect[base + cursor[b, t]] = g
                                cursor[b, t] += 1
                            k += 1

    return tile_sort


@ti.func
def write_keys(depth: ti.template(), rect: ti.template(), ntiles: ti.template(), offsets: ti.template(), tiles_x,
               num_tiles, num_poses, num_gaussians, keys: ti.template(), ids: ti.template(), ellipse: ti.template()):
    """Parallel binning, step 1 (one thread per pose and Gaussian): depth [B, >= N] f32, rect
    [B, >= N, footprint.RECT_SIZE] i32 (tile box and footprint mask), ntiles [B, >= N] i32, offsets [B * N] i64
    (exclusive prefix sum of ntiles over pose-major (pose, Gaussian)) -> keys [>= M] i64 ``(pose * num_tiles +
    tile) << 32 | depth bits`` (depths are positive, so their bits order like the values) and ids [>= M] i32
    (Gaussian index), M = the sum of ntiles: one key per tile of the Gaussian's footprint (its box without
    ``ellipse``)."""
    for b, i in ti.ndrange(num_poses, num_gaussians):
        if ntiles[b, i] > 0:
            k = ti.cast(offsets[b * num_gaussians + i], ti.i32)
            low = ti.cast(ti.bit_cast(depth[b, i], ti.i32), ti.i64)
            mask = read_mask(rect, b, i, ellipse)
            q = 0
            for ty in range(rect[b, i, 1], rect[b, i, 3]):
                for tx in range(rect[b, i, 0], rect[b, i, 2]):
                    if in_footprint(mask, q, ellipse):
                        keys[k] = (ti.cast(b * num_tiles + ty * tiles_x + tx, ti.i64) << 32) | low
                        ids[k] = i
                        k += 1
                    q += 1


@ti.func
def tile_starts(keys: ti.template(), m, num_poses, num_tiles, counts: ti.template(), tile_start: ti.template()):
    """Parallel binning, last step: each tile's start in the sorted keys [M] (relative to its pose's first entry)
    into tile_start [B, num_tiles + 1] (the last column: the pose's total); counts [>= B * num_tiles] scratch."""
    for j in range(num_poses * num_tiles):
        counts[j] = 0
    for k in range(m):
        ti.atomic_add(counts[ti.cast(keys[k] >> 32, ti.i32)], 1)
    for b in range(num_poses):
        acc = 0
        tile_start[b, 0] = 0
        for t in range(num_tiles):
            acc += counts[b * num_tiles + t]
            tile_start[b, t + 1] = acc


@functools.cache
def offsets_kernel():
    """Parallel binning, before the lists are sized: the exclusive prefix sum of ntiles [B, >= N] (pose-major)
    into offsets [B * N + 1] and each pose's total into ``totals`` [B] (a host array: back with the launch)."""

    @ti.kernel
    def offsets_and_totals(ntiles: ti.types.ndarray(dtype=ti.i32, ndim=2), num_poses: ti.i32, num_gaussians: ti.i32,
                           bs: ti.i32, sums: ti.types.ndarray(dtype=ti.i64, ndim=1),
                           offsets: ti.types.ndarray(dtype=ti.i64, ndim=1),
                           totals: ti.types.ndarray(dtype=ti.i64, ndim=1)):
        scan_rows(ntiles, num_poses, num_gaussians, bs, sums, offsets)
        for b in range(num_poses):
            totals[b] = offsets[(b + 1) * num_gaussians] - offsets[b * num_gaussians]

    return offsets_and_totals


@functools.cache
def lists_kernel(num_passes: int, ellipse: bool):
    """Parallel binning once the lists are sized, in one launch: the keys (:func:`write_keys`; ``ellipse``: by
    footprint mask), ``num_passes`` radix passes (``radix.sort_passes``) and the tile starts (:func:`tile_starts`)."""
    sort = sort_passes(num_passes)
    i64, i32 = ti.i64, ti.i32

    @ti.kernel
    def sorted_lists(depth: ti.types.ndarray(dtype=ti.f32, ndim=2), rect: ti.types.ndarray(dtype=i32, ndim=3),
                     ntiles: ti.types.ndarray(dtype=i32, ndim=2), offsets: ti.types.ndarray(dtype=i64, ndim=1),
                     tiles_x: i32, num_tiles: i32, num_poses: i32, num_gaussians: i32, m: i32, bs: i32, nb: i32,
                     scan_bs: i32, keys: ti.types.ndarray(dtype=i64, ndim=1), ids: ti.types.ndarray(dtype=i32, ndim=1),
                     keys_tmp: ti.types.ndarray(dtype=i64, ndim=1), ids_tmp: ti.types.ndarray(dtype=i32, ndim=1),
                     counts: ti.types.ndarray(dtype=i32, ndim=2), sums: ti.types.ndarray(dtype=i64, ndim=1),
                     digit_offsets: ti.types.ndarray(dtype=i64, ndim=1),
                     tile_counts: ti.types.ndarray(dtype=i32, ndim=1), tile_start: ti.types.ndarray(dtype=i32, ndim=2)):
        write_keys(depth, rect, ntiles, offsets, tiles_x, num_tiles, num_poses, num_gaussians, keys, ids, ellipse)
        sort(keys, ids, keys_tmp, ids_tmp, m, bs, nb, scan_bs, counts, sums, digit_offsets)
        if ti.static(num_passes % 2 == 0):
            tile_starts(keys, m, num_poses, num_tiles, tile_counts, tile_start)
        else:
            tile_starts(keys_tmp, m, num_poses, num_tiles, tile_counts, tile_start)

    return sorted_lists


def bin_parallel(depth, rect, ntiles, offsets, num_poses: int, num_gaussians: int, tiles_x: int, num_tiles: int,
                 lists, scratch, tile_start, tile_counts, ellipse: bool):
    """Tile lists of ``num_poses`` poses by a parallel key sort, every step a Taichi kernel.

    Args:
        depth [B, >= N] f32, rect [B, >= N, footprint.RECT_SIZE] i32, ntiles [B, >= N] i32: the projection's outputs.
        offsets: int64 [>= B * N + 1] scratch (the exclusive prefix sum of ``ntiles``, pose-major).
        lists: ``lists(M)`` -> buffers with ``keys`` / ``keys_tmp`` (int64) and ``ids`` / ``ids_tmp`` (int32) of at
            least M entries; its ``isect`` is set to the buffer that ends up holding the lists.
        scratch: ``radix.radix_sort``'s ``counts``, ``offsets`` and ``sums``.
        tile_start: [B, num_tiles + 1] int32; its first ``num_poses`` rows receive each tile's start relative to
            the pose's first entry (the last column: the pose's total). tile_counts: int32 [>= B * num_tiles].
        ellipse: bin by the footprint masks the projection wrote (its ``ellipse_tiles``), else by box.

    Returns:
        totals [num_poses] int64 (numpy): entries per pose; the lists hold each pose's entries from the sum of the
        earlier poses' totals, as the serial sort writes them.
    """
    B, n = num_poses, num_gaussians
    totals = np.empty(B, np.int64)  # a host array: the totals come back with the launch
    launcher(offsets_kernel())(ntiles, B, n, block_size(B * n), scratch.sums, offsets, totals)
    m = int(totals.sum())
    buf = lists(m)
    num_passes = passes(32 + max(1, (B * num_tiles - 1).bit_length()))
    launcher(lists_kernel(num_passes, ellipse))(depth, rect, ntiles, offsets, tiles_x, num_tiles, B, n, m,
                                                *blocks(m), buf.keys, buf.ids, buf.keys_tmp, buf.ids_tmp,
                                                scratch.counts, scratch.sums, scratch.offsets, tile_counts,
                                                tile_start)
    buf.isect = buf.ids if num_passes % 2 == 0 else buf.ids_tmp
    return totals
