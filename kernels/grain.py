"""One task per work item of a coarse parallel loop on the CPU backend.

Taichi 1.7's CPU backend hands each thread-pool task 512 consecutive iterations of a parallel range-for whose
bounds are known only at run time, whatever ``ti.loop_config(block_dim=...)`` or ``cpu_block_dim_adaptive`` say
(measured on this 2-core machine: 130 or 520 heavy iterations take the same time on 1 and 2 threads, 1040 take
half). A loop over a few hundred heavy items, such as the tiles of a few poses, the rows of a few images or the
poses of a batch, therefore ran on one thread. Such loops iterate over ``items * spread()`` and work on every
``spread()``-th iteration (:func:`item`), so that each item is a task of its own; an empty iteration costs about
a nanosecond, an item tens of microseconds or more. On GPUs (one thread per iteration) ``spread()`` is 1.
The work of each item, and so every result, is the same either way.
"""

import taichi as ti

CPU_TASK_ITERATIONS = 512


def spread() -> int:
    """Iterations per item for the backend Taichi runs on (read while a kernel is compiled)."""
    return CPU_TASK_ITERATIONS if ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64) else 1


@ti.func
def item(task, stride: ti.template(), inner):
    """(is_item, outer, inner index) of iteration ``task`` of a loop over ``outer * inner * stride``: ``is_item``
    on every ``stride``-th iteration, which then works on item ``(outer, inner)``."""
    i = task // stride
    return task % stride == 0, i // inner, i % inner
