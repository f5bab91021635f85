"""The first rows (poses) of a device buffer, read back to the host.

A workspace holds images for its whole batch (at least 14 poses), and ``Ndarray.to_numpy`` copies all of it. This
kernel copies the rows asked for into a host array (on the CPU backend Taichi writes the host array in place; on
CUDA it moves only that array).
"""

import functools

import taichi as ti


@functools.cache
def readback_kernel():
    """``readback(src [B, ...], dst [n, ...])``: dst = src[:n], for any dtype and rank (instantiated per pair)."""

    @ti.kernel
    def readback(src: ti.types.ndarray(), dst: ti.types.ndarray()):
        for idx in ti.grouped(dst):
            dst[idx] = src[idx]

    return readback
