"""HLoc's files: results (8 columns ``name qw qx qy qz tx ty tz``) and the query list with intrinsics.

The refinement step that runs on them is :mod:`hgsloc_plugin.hloc_step` (it sits above the adapters). For
pipelines written against earlier releases, ``adapters.hloc.main`` and ``python -m
hgsloc_plugin.adapters.hloc`` still run that step: they are aliases that forward to it.
"""

from __future__ import annotations

from .intrinsics import from_query_list, parse_query_list
from .posefile import PoseFile, write_poses
from .posefile import read_poses as _read

__all__ = ["from_query_list", "main", "parse_query_list", "read_poses", "write_poses"]


def read_poses(path) -> PoseFile:
    """An hloc results file (``name qw qx qy qz tx ty tz``, world-to-camera)."""
    return _read(path, "hloc")


def main(*args, **kwargs):
    """Alias of :func:`hgsloc_plugin.hloc_step.main` (kept for existing pipelines)."""
    from hgsloc_plugin.hloc_step import main as step

    return step(*args, **kwargs)


if __name__ == "__main__":
    import sys

    from hgsloc_plugin.hloc_step import cli

    sys.exit(cli())
