"""The pose-file formats, by name, and the one entry point that reads any of them (``read_poses``).

A line-based dialect is parsed by ``posefile.py`` from its column count; a structured file (a 3DGS trainer's
``cameras.json``) by its own reader. A new format is one :class:`Dialect` entry here and its reader.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .posefile import COLUMNS, PoseFile, read_text_poses
from .trainer import read_cameras_json


@dataclass(frozen=True)
class Dialect:
    """A pose-file format: its name, tokens per record line (None: not line-based), the file suffix it is
    recognised by (None: by its lines), its reader, and a one-line description."""

    name: str
    columns: int | None
    suffix: str | None
    reader: Callable[[Path], PoseFile] | None
    summary: str


def _text(name: str) -> Callable[[Path], PoseFile]:
    return lambda path: read_text_poses(path, name)


#: every format, by name
DIALECTS: dict[str, Dialect] = {d.name: d for d in (
    Dialect("hloc", COLUMNS["hloc"], None, _text("hloc"), "name qw qx qy qz tx ty tz (world-to-camera)"),
    Dialect("ace", COLUMNS["ace"], None, _text("ace"), "hloc's columns + rotation error, translation error, "
            "RANSAC inliers"),
    Dialect("marepo", COLUMNS["marepo"], None, _text("marepo"), "hloc's columns amid printed error tensors"),
    Dialect("pgt", COLUMNS["pgt"], None, _text("pgt"), "name qw qx qy qz tx ty tz focal (7-Scenes pseudo GT)"),
    Dialect("generic", COLUMNS["generic"], None, _text("generic"), "hloc's columns, any image names"),
    Dialect("cambridge", COLUMNS["cambridge"], None, _text("cambridge"),
            "3 header lines, then name X Y Z qw qx qy qz (camera centre)"),
    Dialect("cameras_json", None, ".json", read_cameras_json, "a 3DGS trainer's cameras.json (written back as "
            "generic)"),
)}


def read_poses(path, dialect: str = "auto") -> PoseFile:
    """Read a pose file of any registered format (``dialect``: "auto" or a name of :data:`DIALECTS`).

    Returns:
        A ``PoseFile``: an ordered mapping name -> world-to-camera Pose (None: a failed prior), written back in
        the same dialect by ``posefile.write_poses``. Raises ValueError naming the file and line of a bad record.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose file not found")
    if dialect == "auto":
        by_suffix = [d for d in DIALECTS.values() if d.suffix and path.suffix.lower() == d.suffix]
        if by_suffix:
            return by_suffix[0].reader(path)
        return read_text_poses(path, "auto")
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r}; choose from {tuple(DIALECTS)}")
    return DIALECTS[dialect].reader(path)
