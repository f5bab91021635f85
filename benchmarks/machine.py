"""What a benchmark's processes run on: the share of CPU time the machine's hypervisor took (Linux ``steal``), and
the code of another checkout to compare with.

On a shared virtual machine the hypervisor may run other guests on this one's cores; Linux counts that time as
``steal`` in ``/proc/stat``. A benchmark's times and its ratios between kernels that use one core and kernels
that use all of them move with it (this 2-core machine: up to half the CPU time while a benchmark runs), so the
benchmarks print it beside their figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


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
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(checkout), str(ROOT), os.environ.get("PYTHONPATH", "")]))


def module_command(file: str, other_checkout: bool = False) -> list[str]:
    """The command that runs the benchmark whose ``__file__`` is ``file`` as ``python -m benchmarks.<name>`` (with
    ``cwd=ROOT``). ``other_checkout`` (run in ``checkout_env``'s environment): with ``-P``, so that the package
    comes from the checkout first on ``PYTHONPATH``, not from the working directory; the benchmarks then come from
    the checkout when it holds them as a package (``benchmarks/__init__.py``), else from this one."""
    return [sys.executable, *(["-P"] if other_checkout else []), "-m", f"benchmarks.{Path(file).stem}"]


def run_child(script: str, checkout: Path | None, args: list[str]) -> dict:
    """Run ``script --child ARGS`` (this checkout's script) importing the package of ``checkout`` (None: this
    checkout's) and return the JSON object its last line prints; it must name, as ``checkout``, the folder its
    package came from, which is checked."""
    env = checkout_env(checkout) if checkout is not None else dict(os.environ)
    p = subprocess.run([*module_command(script, checkout is not None), "--child", *args], capture_output=True,
                       text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"child failed ({checkout or ROOT}, {args}):\n{p.stderr[-3000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    if Path(out["checkout"]) != (checkout or ROOT).resolve():
        raise RuntimeError(f"the child imported the package from {out['checkout']}, not {checkout or ROOT}")
    return out


def alternate(before: Path, rounds: int, measure: Callable[[Path | None], dict], label: str,
              show: Callable[[dict], str] = str) -> tuple[dict[str, list[dict]], float]:
    """``measure(before)`` and ``measure(None)`` (this checkout) alternately, ``rounds`` times each: ({"before":
    [...], "now": [...]}, the hypervisor's share of the CPU time meanwhile). Each result goes to stderr as
    ``show`` writes it, under ``label``."""
    got: dict[str, list[dict]] = {"before": [], "now": []}
    with StealClock() as steal:
        for _ in range(rounds):
            for side, path in (("before", before), ("now", None)):
                got[side].append(measure(path))
                print(f"{label} {side}: {show(got[side][-1])}", file=sys.stderr, flush=True)
    return got, steal.share


def before_parser(doc: str, cases: list[str]) -> argparse.ArgumentParser:
    """The options of a benchmark that compares this checkout with another one's (``--before DIR``, ``--cases``,
    ``--rounds``, ``--out``, and the hidden ``--child CASE`` its own child processes run)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", type=Path, help="the checkout to measure as the reference (see above)")
    ap.add_argument("--cases", nargs="+", default=cases)
    ap.add_argument("--rounds", type=int, default=3, help="processes per side and case, alternating")
    ap.add_argument("--out", type=Path, help="also write the Markdown table here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    return ap


def before_args(ap: argparse.ArgumentParser, child: Callable[[argparse.Namespace], dict]
                ) -> tuple[argparse.Namespace, Path] | None:
    """Parse ``ap`` (``before_parser``'s). In a ``--child`` process: print ``child(args)`` as one JSON line (what
    ``run_child`` reads) and return None. Else (args, ``--before``'s checkout resolved and checked by
    ``checkout_env`` before any run); a usage error without ``--before``."""
    a = ap.parse_args()
    if a.child:
        print(json.dumps(child(a)))
        return None
    if a.before is None:
        ap.error("--before DIR is required (the checkout to compare with)")
    before = a.before.resolve()
    checkout_env(before)
    return a, before


def write_before_table(out: Path, title: str, script: str, setup: str, rows: list[str], args: str = "") -> None:
    """Write a ``--before`` benchmark's table to ``out`` (its notes kept, ``harness.write_keeping_notes``):
    the heading ``title`` of ``benchmarks/<script>``, the command that regenerates it (with ``args``, the run's
    own options), the ``setup`` line, the table's ``rows``."""
    from benchmarks.harness import write_keeping_notes

    write_keeping_notes(out, [f"# {title} (`benchmarks/{script}`)", "",
                              f"Regenerate: `python -m benchmarks.{Path(script).stem} --before DIR "
                              f"{args + ' ' if args else ''}--out {out}`",
                              "(DIR: the checkout before the change, see the script).", "", setup, "", *rows])
