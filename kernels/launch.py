"""Kernel launches with less host time: Taichi's checks made once per argument signature, not at every call.

Taichi 1.7 spends 0.2-0.8 ms of Python on each launch of the renderer's kernels (13-20 arguments; the kernels
themselves run 0.6-1.3 ms a render on a GPU): it derives every argument's features to look the compiled kernel
up, and sets each argument through a chain of type tests. A query launches about 90 of them, so on a GPU the
host, not the device, sets the pace (``benchmarks/throughput.md``, host ms per query).

:func:`launcher` wraps a ``@ti.kernel``. The first call with a new argument signature (each argument's type,
and for arrays their dtype, rank and contiguity) goes through Taichi's own path, which compiles and checks
everything; the wrapper then keeps the compiled kernel and one setter per argument, and the next calls of that
signature only set the arguments and launch. The kernels, their arguments and so every result are those of
Taichi's path. A signature the fast path does not cover (template or matrix arguments, return values, prints,
autodiff, a non-contiguous host array) keeps Taichi's path; so does a Taichi reset (a new program).
:func:`empty` makes a device array without Taichi's zero fill, for arrays an upload or a kernel fills whole.
Written against Taichi 1.7's internals (``kernel_impl.Kernel``, ``ScalarNdarray``), the version the package pins;
``HGSLOC_FAST_LAUNCH=0`` turns both off. :func:`timed_launches` times the launches made through launchers (for
measurements).
"""

from __future__ import annotations

import contextlib
import functools
import os
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import taichi as ti
from taichi._lib import core as _ti_core
from taichi.lang import impl
from taichi.lang._ndarray import Ndarray, ScalarNdarray
from taichi.lang.enums import AutodiffMode, Layout
from taichi.lang.util import cook_dtype
from taichi.types import ndarray_type, primitive_types
from taichi.types.utils import is_signed

_ENABLED = os.environ.get("HGSLOC_FAST_LAUNCH", "1") != "0"


@dataclass
class LaunchTimes:
    """The launches made through :class:`Launcher` inside :func:`timed_launches`.

    Attributes:
        count: how many.
        seconds: the seconds in Taichi's launch call (on the CPU the kernel's run, on CUDA the enqueue and any wait
            for a host array); a signature's first call, or one the fast path does not cover, counts Taichi's
            whole call. What the launcher spends setting arguments stays outside (host time).
        by_kernel: those seconds per kernel name ({name: s}).
    """

    count: int = 0
    seconds: float = 0.0
    by_kernel: dict[str, float] = field(default_factory=lambda: defaultdict(float))

    def add(self, name: str, seconds: float) -> None:
        self.count += 1
        self.seconds += seconds
        self.by_kernel[name] += seconds


_TIMERS: list[LaunchTimes] = []  # the active timers, innermost last


@contextlib.contextmanager
def timed_launches() -> Iterator[LaunchTimes]:
    """The launches made inside, counted in the :class:`LaunchTimes` yielded; with timers nested, each launch counts
    in the innermost only (so that an inner measurement can be left out of an outer one)."""
    times = LaunchTimes()
    _TIMERS.append(times)
    try:
        yield times
    finally:
        _TIMERS.remove(times)


def _signature(value) -> tuple:
    """What Taichi's compiled-kernel lookup and argument checks depend on, for one argument."""
    if isinstance(value, ti.Ndarray):
        return (ti.Ndarray, value.dtype, len(value.shape), value.grad is None)
    if isinstance(value, np.ndarray):
        return (np.ndarray, value.dtype.str, value.ndim, value.flags.c_contiguous)
    return (type(value),)


def _set_float(ctx, index, value):
    ctx.set_arg_float(index, float(value))


def _set_int(ctx, index, value):
    ctx.set_arg_int(index, int(value))


def _set_uint(ctx, index, value):
    ctx.set_arg_uint(index, int(value))


def _set_ndarray(ctx, index, value):
    ctx.set_arg_ndarray(index, value.arr)


def _set_host_array(ctx, index, value):
    ctx.set_arg_external_array_with_shape(index, int(value.ctypes.data), value.nbytes, value.shape, 0)


def _setter(annotation, value):
    """How one argument is set on a launch context, or None when only Taichi's path handles it."""
    if id(annotation) in primitive_types.real_type_ids:
        return _set_float
    if id(annotation) in primitive_types.integer_type_ids:
        return _set_int if is_signed(cook_dtype(annotation)) else _set_uint
    if isinstance(annotation, ndarray_type.NdarrayType):
        if annotation.dtype is not None and id(annotation.dtype) not in primitive_types.type_ids:
            return None  # vector or matrix elements: Taichi strips their dimensions from the shape
        if isinstance(value, ti.Ndarray) and value.grad is None:
            return _set_ndarray
        if isinstance(value, np.ndarray) and value.flags.c_contiguous:
            return _set_host_array
    return None


class Launcher:
    """A ``@ti.kernel`` called with its arguments as Taichi's ``kernel(*args)``, faster from the second call of an
    argument signature (module docstring)."""

    def __init__(self, kernel):
        self.kernel = kernel
        self.primal = getattr(kernel, "_primal", None)
        self.plans: dict[tuple, tuple | None] = {}
        self.name = getattr(kernel, "__name__", None) or getattr(self.primal, "func", kernel).__name__

    def __call__(self, *args):
        sig = tuple(_signature(a) for a in args)
        plan = self.plans.get(sig, False)
        prog = impl.get_runtime().prog
        timer = _TIMERS[-1] if _TIMERS else None  # timed_launches' innermost
        if plan and plan[0] is prog and impl.get_runtime().target_tape is None:
            _, t_kernel, data, setters = plan
            ctx = t_kernel.make_launch_context()
            for i, (set_arg, value) in enumerate(zip(setters, args)):
                set_arg(ctx, (i,), value)
            t0 = time.perf_counter()
            prog.launch_kernel(data, ctx)
            if timer is not None:
                timer.add(self.name, time.perf_counter() - t0)
            return None
        t0 = time.perf_counter()
        out = self.kernel(*args)
        if timer is not None:
            timer.add(self.name, time.perf_counter() - t0)
        if plan is False or (plan is not None and plan[0] is not prog):
            self.plans[sig] = self._plan(args)
        return out

    def _plan(self, args) -> tuple | None:
        """(program, compiled kernel, its launch data, setters) for ``args``' signature, or None."""
        k = self.primal
        if not _ENABLED or k is None or k.return_type is not None or getattr(k, "has_print", True):
            return None
        if k.autodiff_mode != AutodiffMode.NONE or len(k.arguments) != len(args):
            return None
        setters = [_setter(a.annotation, v) for a, v in zip(k.arguments, args)]
        if any(s is None for s in setters):
            return None
        key = k.ensure_compiled(*args)
        t_kernel = k.compiled_kernels[key]
        prog = impl.get_runtime().prog
        data = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
        return prog, t_kernel, data, setters


@functools.cache
def launcher(kernel) -> Launcher:
    """The :class:`Launcher` of ``kernel`` (one per kernel object, so its plans are shared by every caller)."""
    return Launcher(kernel)


def upload(dst: ti.Ndarray, values: np.ndarray) -> None:
    """``dst.from_numpy(values)`` through a :class:`Launcher` of Taichi's own copy kernel: the same shape required,
    the values cast to ``dst``'s element type, as there."""
    from taichi._kernels import ext_arr_to_ndarray

    if tuple(dst.shape) != tuple(values.shape):
        raise ValueError(f"shape mismatch: {tuple(dst.shape)} expected, {tuple(values.shape)} given")
    launcher(ext_arr_to_ndarray)(np.ascontiguousarray(values), dst)
    impl.get_runtime().sync()


def empty(dtype, shape: tuple[int, ...]) -> ti.Ndarray:
    """A scalar device array like ``ti.ndarray(dtype, shape)`` whose elements are not set: for an array that an
    upload or a kernel fills entirely before anything reads it. Taichi zero-fills every new array (0.9 ms for the
    2.7 MB of a 320x240 query's statistics on the CPU, a fill launch on CUDA) and formats the caller's Python
    traceback for its debug information; this array skips both. Taichi's own path where its internals differ
    (and with ``HGSLOC_FAST_LAUNCH=0``)."""
    shape = tuple(int(s) for s in shape)
    prog = impl.get_runtime().prog
    if _ENABLED and prog is not None and shape and all(0 < s < 2 ** 31 for s in shape):
        try:
            dt = cook_dtype(dtype)
            arr = prog.create_ndarray(dt, shape, layout=Layout.NULL, zero_fill=False, dbg_info=_ti_core.DebugInfo(""))
        except (AttributeError, TypeError):
            arr = None
        if arr is not None:  # the Python object ti.ndarray wraps around it (ScalarNdarray.__init__'s fields)
            nd = ScalarNdarray.__new__(ScalarNdarray)
            Ndarray.__init__(nd)
            nd.dtype = nd.element_type = dt
            nd.arr, nd.shape = arr, tuple(arr.shape)
            return nd
    return ti.ndarray(dtype, shape)
