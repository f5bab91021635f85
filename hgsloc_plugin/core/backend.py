"""The one place that chooses and starts the Taichi backend.

``init(arch="auto" | "cpu" | "cuda")`` starts Taichi once per process; the environment variable
``HGSLOC_ARCH`` gives the default. "auto" takes CUDA when Taichi finds it, else the CPU; ``HGSLOC_CPU_THREADS``
caps the CPU backend's threads (e.g. several processes sharing one machine's cores). Kernels are cached on disk
by Taichi's offline cache (``HGSLOC_CACHE_DIR``, default ``~/.cache/hgsloc_plugin/taichi``; one set per CPU
thread count) so a second process does not recompile them, and Taichi's front end, which still runs in every
process, is memoised where it repeats itself (``kernel_load.py``). On the CPU, Taichi's control-flow-graph
optimisation is off: it took most of the compile time (a user's first query 113 s -> 36 s,
``benchmarks/startup_cold.md``).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
from pathlib import Path

logger = logging.getLogger("hgsloc_plugin")

_ARCH: str | None = None
_VALID = ("auto", "cpu", "cuda")


def _cache_dir() -> str:
    default = Path.home() / ".cache" / "hgsloc_plugin" / "taichi"
    return str(Path(os.environ.get("HGSLOC_CACHE_DIR", default)))


def lod_cache_dir() -> Path:
    """Where maps' level-of-detail hierarchies are cached (``render/hierarchy.py``): ``HGSLOC_LOD_CACHE_DIR``,
    default ``~/.cache/hgsloc_plugin/hierarchy``."""
    default = Path.home() / ".cache" / "hgsloc_plugin" / "hierarchy"
    return Path(os.environ.get("HGSLOC_LOD_CACHE_DIR", default))


def requested_arch(arch: str | None = None) -> str:
    """The backend asked for: ``arch``, else ``HGSLOC_ARCH``, else "auto"; lower case, checked to be one of
    "auto", "cpu", "cuda"."""
    requested = (arch or os.environ.get("HGSLOC_ARCH", "auto")).lower()
    if requested not in _VALID:
        raise ValueError(f"arch must be one of {_VALID}, got {requested!r} (from argument or HGSLOC_ARCH)")
    return requested


def requested_cpu_threads() -> int | None:
    """``HGSLOC_CPU_THREADS`` as a positive int, or None when unset or empty."""
    text = os.environ.get("HGSLOC_CPU_THREADS", "").strip()
    if not text:
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"HGSLOC_CPU_THREADS must be a positive integer, got {text!r}")
    return n


def init(arch: str | None = None, *, debug: bool = False, cpu_threads: int | None = None) -> str:
    """Start Taichi on the chosen backend; later calls return the backend already chosen.

    Args:
        arch: "auto", "cpu" or "cuda"; None reads ``HGSLOC_ARCH`` (default "auto").
        debug: Taichi debug mode (bounds checks), for development only.
        cpu_threads: number of CPU threads for the CPU backend; None reads ``HGSLOC_CPU_THREADS`` (default: all
            cores).

    Returns:
        The backend in use, "cpu" or "cuda".
    """
    global _ARCH
    requested = requested_arch(arch)
    if cpu_threads is None:
        cpu_threads = requested_cpu_threads()
    if _ARCH is not None:
        if requested not in ("auto", _ARCH):
            raise RuntimeError(
                f"Taichi already started on {_ARCH!r}; call hgsloc_plugin.init({requested!r}) before any rendering"
            )
        return _ARCH
    with contextlib.redirect_stdout(sys.stderr):  # Taichi prints its banner and arch line on stdout
        _ARCH = _start(requested, debug, cpu_threads)
    compile_notice(_ARCH, cpu_threads)
    return _ARCH


def compile_notice(arch: str, cpu_threads: int | None) -> None:
    """Say that kernels compile as first used when this cache holds no earlier run of this backend and thread
    count (a marker file, written when the process exits), instead of half a minute without a word."""
    import atexit

    n = cpu_threads or os.cpu_count() or 1
    marker = Path(_cache_dir()) / f".hgsloc-{arch}-{n if arch == 'cpu' else 'gpu'}-threads.warm"
    if marker.exists():
        return
    logger.warning("first run on this machine (%s%s): the renderer's kernels compile as they are first used, about "
                   "30 s on a 2-core CPU, and are cached in %s for later runs", arch,
                   f", {n} threads" if arch == "cpu" else "", marker.parent)

    def mark() -> None:
        with contextlib.suppress(OSError):
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.touch()

    atexit.register(mark)


def _start(requested: str, debug: bool, cpu_threads: int | None) -> str:
    import taichi as ti

    from .kernel_load import memoize_source_info

    memoize_source_info()  # kernel loading 2-3x faster in each new process (kernel_load.py)

    kwargs = dict(
        offline_cache=True,
        offline_cache_file_path=_cache_dir(),
        debug=debug,
        log_level=ti.WARN,
        default_fp=ti.f32,
        random_seed=0,
    )
    if cpu_threads:
        kwargs["cpu_max_num_threads"] = int(cpu_threads)
    if requested == "auto" and not _cuda_driver_present():
        requested = "cpu"
    if requested in ("auto", "cuda"):
        try:
            ti.init(arch=ti.cuda, **kwargs)
            if ti.lang.impl.current_cfg().arch == ti.cuda:
                logger.info("Taichi started on CUDA")
                return "cuda"
        except Exception as exc:  # pragma: no cover - depends on the machine
            if requested == "cuda":
                raise RuntimeError(f"CUDA backend requested but unavailable: {exc}") from exc
        if requested == "cuda":
            raise RuntimeError("CUDA backend requested but Taichi fell back to another arch")
        ti.reset()
    # without Taichi's control-flow-graph pass (store forwarding, dead stores; LLVM does both for the CPU): kernels
    # compile 3-5x faster and run as fast (benchmarks/startup_cold.md)
    ti.init(arch=ti.cpu, cfg_optimization=False, **kwargs)
    logger.info("Taichi started on CPU")
    return "cpu"


def _cuda_driver_present() -> bool:
    """True when the CUDA driver library can be loaded (checked without starting Taichi)."""
    import ctypes

    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def current_arch() -> str:
    """The backend in use, starting the default one if nothing was started yet."""
    return _ARCH if _ARCH is not None else init()


#: queries a lockstep batch advances together by default (``batch.run_batch``'s ``batch_size``), per backend: on
#: the GPU a launch of many queries' poses fills the device; on the CPU a few fill the cores' work queues
DEFAULT_BATCH_SIZE = {"cpu": 4, "cuda": 32}


def default_batch_size() -> int:
    """The default ``batch_size`` of the backend in use (``DEFAULT_BATCH_SIZE``)."""
    return DEFAULT_BATCH_SIZE[current_arch()]


#: how much larger than a group's largest working set the union a lockstep launch renders from may be
#: (``lockstep.Lockstep``'s ``union_limit``), per backend. The CPU: 1, no union (the densified room's 975k
#: Gaussians, batches of 4: 0.72x the sequential speed with unions of up to 2x, 1.02x without;
#: ``benchmarks/throughput.md``): its kernels already fill the cores, and a union's extra Gaussians are extra
#: projection work for every pose. CUDA: any union (up to the whole map, there 1.5x a working set's render time,
#: ``benchmarks/map_scale.md``), so a batch of 32 queries shares its launches; not yet measured in batches.
DEFAULT_UNION_LIMIT = {"cpu": 1.0, "cuda": math.inf}


def default_union_limit() -> float:
    """The default ``union_limit`` of the backend in use (``DEFAULT_UNION_LIMIT``)."""
    return DEFAULT_UNION_LIMIT[current_arch()]
