"""What a benchmark's processes run on: the share of CPU time the machine's hypervisor took (Linux ``steal``), and
the code of another checkout to compare with.

On a shared virtual machine the hypervisor may run other guests on this one's cores; Linux counts that time as
``steal`` in ``/proc/stat``. A benchmark's times and its ratios between kernels that use one core and kernels
that use all of them move with it (this 2-core machine: up to half the CPU time while a benchmark runs), so the
benchmarks print it beside their figures.
"""

from __future__ import annotations

import os
from pathlib import Path


def cpu_ticks() -> tuple[int, int] | None:
    """(all CPU ticks, steal ticks) since boot, summed over the cores; None where ``/proc/stat`` is missing."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
    except OSError:
        return None
    if fields[0] != "cpu" or len(fields) < 9:
        return None
    ticks = [int(x) for x in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return sum(ticks), ticks[7]


class StealClock:
    """Context manager: ``share`` is the fraction of CPU time stolen while inside (nan where unknown)."""

    def __enter__(self) -> StealClock:
        self.start, self.share = cpu_ticks(), float("nan")
        return self

    def __exit__(self, *exc) -> None:
        end = cpu_ticks()
        if self.start is not None and end is not None and end[0] > self.start[0]:
            self.share = (end[1] - self.start[1]) / (end[0] - self.start[0])


def checkout_env(checkout: Path) -> dict[str, str]:
    """The environment of a process that imports the package from ``checkout`` (the code before a change: a ``git
    worktree`` with ``hgsloc_plugin/kernels`` and ``hgsloc_plugin/adapters`` linked to its ``kernels/`` and
    ``adapters/``, which the editable install maps only for its own checkout): ``PYTHONPATH`` with the checkout
    first. Exits with a message when the links are missing."""
    checkout = checkout.resolve()
    if not (checkout / "hgsloc_plugin" / "kernels").exists():
        raise SystemExit(f"{checkout}: no hgsloc_plugin/kernels (link it to the checkout's kernels/)")
    return dict(os.environ, PYTHONPATH=str(checkout) + os.pathsep + os.environ.get("PYTHONPATH", ""))
