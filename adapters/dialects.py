"""The pose-file formats, by name, and the one entry point that reads any of them (``read_poses``).

A line-based dialect is parsed by ``posefile.py`` from its column count; a structured file (a 3DGS trainer's
``cameras.json``) by its own reader. A new format is one :class:`Dialect` entry here and its reader.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .nerf import DIALECT as TRANSFORMS_JSON
from .nerf import is_transforms_json, read_transforms_json, write_transforms_json
from .posefile import COLUMNS, PoseFile, read_text_poses, write_text_poses
from .trainer import read_cameras_json


@dataclass(frozen=True)
class Dialect:
    """A pose-file format: its name, tokens per record line (None: not line-based), how a file of it is recognised
    before its lines are read (None: by its lines), its reader, its writer (None: the line writer), and a one-line
    description."""

    name: str
    columns: int | None
    recognise: Callable[[Path], bool] | None
    reader: Callable[[Path], PoseFile]
    summary: str
    writer: Callable | None = None


def _text(name: str) -> Callable[[Path], PoseFile]:
    return lambda path: read_text_poses(path, name)


#: every format, by name
DIALECTS: dict[str, Dialect] = {d.name: d for d in (
    Dialect(TRANSFORMS_JSON, None, is_transforms_json, read_transforms_json, "NeRF / instant-ngp transforms.json "
            "(camera-to-world, OpenGL axes)", write_transforms_json),
    Dialect("hloc", COLUMNS["hloc"], None, _text("hloc"), "name qw qx qy qz tx ty tz (world-to-camera)"),
    Dialect("ace", COLUMNS["ace"], None, _text("ace"), "hloc's columns + rotation error, translation error, "
            "RANSAC inliers"),
    Dialect("marepo", COLUMNS["marepo"], None, _text("marepo"), "hloc's columns amid printed error tensors"),
    Dialect("pgt", COLUMNS["pgt"], None, _text("pgt"), "name qw qx qy qz tx ty tz focal (7-Scenes pseudo GT)"),
    Dialect("generic", COLUMNS["generic"], None, _text("generic"), "hloc's columns, any image names"),
    Dialect("cambridge", COLUMNS["cambridge"], None, _text("cambridge"),
            "3 header lines, then name X Y Z qw qx qy qz (camera centre)"),
    Dialect("cameras_json", None, lambda p: p.suffix.lower() == ".json", read_cameras_json,
            "a 3DGS trainer's cameras.json (written back as generic)"),
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
        for d in DIALECTS.values():  # in order: transforms.json before any other .json
            if d.recognise is not None and d.recognise(path):
                return d.reader(path)
        return read_text_poses(path, "auto")
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r}; choose from {tuple(DIALECTS)}")
    return DIALECTS[dialect].reader(path)


def write_poses(path, poses, like: PoseFile) -> Path:
    """Write ``like``'s file in its own format with the poses in ``poses`` replaced (atomic; never over the input):
    a line dialect keeps every other byte, ``transforms.json`` every other field."""
    d = DIALECTS.get(like.dialect)
    return (d.writer if d is not None and d.writer is not None else write_text_poses)(path, poses, like)
