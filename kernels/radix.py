"""Parallel scan and stable LSD radix sort on the device, in Taichi (the GPU's tile sort, ``tile_sort.bin_parallel``).

Both split their input into blocks, one thread per block, and are deterministic: a block's thread walks its
entries in order, so equal keys keep their input order (the sort is stable) and every result is the same on every
backend and run. Shapes: ``m`` entries; ``nb`` blocks of ``bs`` entries.

- scan: per-block sums, an exclusive scan of the sums on one thread, then each block's entries from its offset.
- radix sort of non-negative int64 keys with int32 values, 8 bits a pass: per (digit, block) counts, their
  exclusive scan in digit-major order (all blocks' entries of digit 0 first, block by block), then each block
  scatters its entries in order.

A scan, and a whole radix sort, are one launch each (their steps are loops of one kernel, run in turn): a launch
costs the host tens of microseconds, and a render's sort made 28 of them.
"""

import functools

import taichi as ti

from .launch import launcher

DIGIT_BITS = 8
DIGITS = 1 << DIGIT_BITS
MAX_BLOCKS = 1024  # blocks of one radix pass: its counts are [DIGITS, MAX_BLOCKS]


def block_size(m: int, blocks: int = MAX_BLOCKS) -> int:
    """Entries per block so that ``m`` entries fit in at most ``blocks`` blocks."""
    return max(64, -(-m // blocks))


@ti.func
def scan_rows(vals: ti.template(), rows, cols, bs, sums: ti.template(), out: ti.template()):
    """Exclusive scan over the first ``cols`` columns of the first ``rows`` rows of ``vals`` (2-D int32), read
    row-major as one sequence of ``rows * cols`` values, as three loops run in turn (each a parallel loop when
    called at a kernel's outermost scope): per-block sums (``bs`` values a block), their exclusive scan on one
    thread, then each block's values from its offset. ``out`` [>= rows * cols + 1] int64 receives the prefix
    sums and, last, the total; ``sums`` int64 [>= blocks + 1] is scratch."""
    n = rows * cols
    nb = (n + bs - 1) // bs
    for blk in range(nb):
        s = ti.i64(0)
        for j in range(blk * bs, ti.min(n, blk * bs + bs)):
            s += vals[j // cols, j % cols]
        sums[blk] = s
    for _ in range(1):  # one thread: the blocks' sums in order
        acc = ti.i64(0)
        for blk in range(nb + 1):
            v = sums[blk] if blk < nb else ti.i64(0)
            sums[blk] = acc
            acc += v
    for blk in range(nb):
        acc = sums[blk]
        for j in range(blk * bs, ti.min(n, blk * bs + bs)):
            out[j] = acc
            acc += vals[j // cols, j % cols]
        if blk == nb - 1:
            out[n] = acc


@functools.cache
def scan_kernel():
    """``scan_rows`` in one launch."""

    @ti.kernel
    def scan(vals: ti.types.ndarray(dtype=ti.i32, ndim=2), rows: ti.i32, cols: ti.i32, bs: ti.i32,
             sums: ti.types.ndarray(dtype=ti.i64, ndim=1), out: ti.types.ndarray(dtype=ti.i64, ndim=1)):
        scan_rows(vals, rows, cols, bs, sums, out)

    return scan


def exclusive_scan(vals, rows: int, cols: int, sums, out) -> None:
    """``out[j]`` = the sum of the first ``j`` of the ``rows * cols`` values of ``vals`` [>= rows, >= cols] (int32,
    row-major), ``out[rows * cols]`` their total; ``sums``: int64 scratch [>= MAX_BLOCKS + 1]."""
    n = rows * cols
    if n == 0:
        raise ValueError("nothing to scan")
    launcher(scan_kernel())(vals, rows, cols, block_size(n), sums, out)


@ti.func
def radix_pass(keys_in: ti.template(), ids_in: ti.template(), m, shift, bs, nb, scan_bs, counts: ti.template(),
               sums: ti.template(), offsets: ti.template(), keys_out: ti.template(), ids_out: ti.template()):
    """One radix pass of the first ``m`` (key, id) pairs on the digit at ``shift``, as loops run in turn: per (digit,
    block) counts [DIGITS, nb] (``bs`` entries a block), their exclusive scan in digit-major order (all blocks'
    entries of digit 0 first, block by block; ``scan_bs`` counts a scan block) into ``offsets``, then each block
    scatters its entries in order (stable)."""
    for d, blk in ti.ndrange(DIGITS, nb):
        counts[d, blk] = 0
    for blk in range(nb):
        for i in range(blk * bs, ti.min(m, blk * bs + bs)):
            d = ti.cast((keys_in[i] >> shift) & (DIGITS - 1), ti.i32)
            counts[d, blk] += 1
    scan_rows(counts, DIGITS, nb, scan_bs, sums, offsets)
    for blk in range(nb):
        for i in range(blk * bs, ti.min(m, blk * bs + bs)):
            k = keys_in[i]
            j = ti.cast((k >> shift) & (DIGITS - 1), ti.i32) * nb + blk
            pos = offsets[j]
            offsets[j] = pos + 1
            keys_out[pos] = k
            ids_out[pos] = ids_in[i]


def passes(bits: int) -> int:
    """Radix passes that sort keys on their lowest ``bits`` bits."""
    return -(-bits // DIGIT_BITS)


def blocks(m: int) -> tuple[int, int, int]:
    """(entries a block, blocks, counts a scan block) of a radix sort of ``m`` entries."""
    bs = block_size(m)
    nb = -(-m // bs)
    return bs, nb, block_size(DIGITS * nb)


@functools.cache
def sort_passes(num_passes: int):
    """A ti.func running ``num_passes`` radix passes (``radix_pass``, lowest digit first) ping-ponging from (keys,
    ids) to (keys_tmp, ids_tmp) and back: the sorted pairs end in (keys, ids) after an even number of passes, else
    in the scratch pair."""

    @ti.func
    def run(keys: ti.template(), ids: ti.template(), keys_tmp: ti.template(), ids_tmp: ti.template(), m, bs, nb,
            scan_bs, counts: ti.template(), sums: ti.template(), offsets: ti.template()):
        for p in ti.static(range(num_passes)):
            if ti.static(p % 2 == 0):
                radix_pass(keys, ids, m, p * DIGIT_BITS, bs, nb, scan_bs, counts, sums, offsets, keys_tmp, ids_tmp)
            else:
                radix_pass(keys_tmp, ids_tmp, m, p * DIGIT_BITS, bs, nb, scan_bs, counts, sums, offsets, keys, ids)

    return run


@functools.cache
def radix_sort_kernel(num_passes: int):
    """:func:`sort_passes` in one launch."""
    run = sort_passes(num_passes)
    i64, i32 = ti.i64, ti.i32

    @ti.kernel
    def radix_sort_passes(keys: ti.types.ndarray(dtype=i64, ndim=1), ids: ti.types.ndarray(dtype=i32, ndim=1),
                          keys_tmp: ti.types.ndarray(dtype=i64, ndim=1), ids_tmp: ti.types.ndarray(dtype=i32, ndim=1),
                          m: i32, bs: i32, nb: i32, scan_bs: i32, counts: ti.types.ndarray(dtype=i32, ndim=2),
                          sums: ti.types.ndarray(dtype=i64, ndim=1), offsets: ti.types.ndarray(dtype=i64, ndim=1)):
        run(keys, ids, keys_tmp, ids_tmp, m, bs, nb, scan_bs, counts, sums, offsets)

    return radix_sort_passes


def radix_sort(keys, ids, keys_tmp, ids_tmp, m: int, bits: int, counts, offsets, sums):
    """Sort the first ``m`` (key, id) pairs by key, stably, on their lowest ``bits`` bits (keys non-negative).

    Args:
        keys / ids: int64 / int32 [>= m], the input; keys_tmp / ids_tmp: the same sizes, scratch.
        counts: int32 [DIGITS, MAX_BLOCKS]; offsets: int64 [DIGITS * MAX_BLOCKS + 1]; sums: int64 [MAX_BLOCKS + 1].

    Returns:
        (keys, ids): the buffers that hold the sorted pairs (the inputs or the scratch ones).
    """
    if m == 0:
        return keys, ids
    n = passes(bits)
    launcher(radix_sort_kernel(n))(keys, ids, keys_tmp, ids_tmp, m, *blocks(m), counts, sums, offsets)
    return (keys, ids) if n % 2 == 0 else (keys_tmp, ids_tmp)
