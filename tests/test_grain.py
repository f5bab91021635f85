"""One task per work item (``kernels/grain.py``): the strided loop visits every item exactly once, whatever the
item count relative to Taichi's 512-iteration CPU tasks.

No ``from __future__ import annotations`` here: Taichi reads the kernel annotations as objects."""

import numpy as np
import pytest
import taichi as ti

import hgsloc_plugin as hp
from hgsloc_plugin.kernels.grain import CPU_TASK_ITERATIONS, item, spread


@pytest.fixture(scope="module")
def visit_kernel():
    hp.init()

    @ti.kernel
    def visit(outer: ti.i32, inner: ti.i32, hits: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        stride = ti.static(spread())
        for task in range(outer * inner * stride):
            is_item, b, i = item(task, stride, inner)
            if is_item:
                k = b * inner + i
                hits[k] += k + 1  # the item's own number: a wrong index or a repeat shows

    return visit


@pytest.mark.parametrize("outer, inner", [(1, 1), (3, 1), (1, 130), (3, 130), (1, 511), (2, 256), (1, 513),
                                          (14, 130), (5, 1000)])
def test_every_item_is_visited_once(visit_kernel, outer, inner):
    n = outer * inner
    hits = np.zeros(n + 7, np.int32)  # room past the end: nothing may be written there
    visit_kernel(outer, inner, hits)
    expected = np.zeros(n + 7, np.int32)
    expected[:n] = np.arange(1, n + 1)
    np.testing.assert_array_equal(hits, expected)


def test_cpu_backend_spreads_items_over_tasks():
    assert hp.init() == "cpu"  # the suite runs on the CPU backend
    assert spread() == CPU_TASK_ITERATIONS == 512
