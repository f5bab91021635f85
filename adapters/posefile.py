"""Pose files of the localizers, read losslessly and written back in the same dialect (CONVENTIONS §2).

A :class:`PoseFile` keeps every line of the input: records (name, pose, extra columns) and any other line
(Marepo's spilled error tensors), so that writing it back with no pose changed gives the same bytes (CRLF
line endings included). A line that starts with an image name but is no whole record is an error naming it
(a lost query, even in raw Marepo output); a skipped line that is not a printed tensor is named in a warning.
Failed priors (non-finite values or a zero quaternion, as ACE writes for an exact identity) are kept with
``pose = None`` and passed through unchanged.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from hgsloc_plugin.core.fileio import atomic_write_bytes
from hgsloc_plugin.core.pose import Pose

logger = logging.getLogger("hgsloc_plugin")
IMAGE_EXT = (".png", ".jpg", ".jpeg")
DIALECTS = ("hloc", "ace", "marepo", "pgt", "generic", "cambridge")
#: tokens per record line of each dialect
COLUMNS = {"hloc": 8, "generic": 8, "marepo": 8, "ace": 11, "pgt": 9, "cambridge": 8}
#: Cambridge Landmarks ``dataset_*.txt``: 3 header lines, then ``name X Y Z W P Q R`` (camera centre,
#: world-to-camera quaternion)
CAMBRIDGE_HEADER = "Visual Landmark Dataset"


@dataclass
class Record:
    """One pose line: raw text, its 1-based line number, name, pose (None = failed prior), all tokens."""

    line_no: int
    raw: str
    name: str
    pose: Pose | None
    tokens: list[str]


@dataclass
class PoseFile(Mapping):
    """An ordered mapping name -> Pose (failed priors map to None) plus what is needed to write it back."""

    path: Path
    dialect: str
    lines: list[str]  # every line without its newline
    records: list[Record] = field(default_factory=list)
    final_newline: bool = True
    bom: bool = False  # the file began with a UTF-8 byte-order mark (written back)

    def __post_init__(self) -> None:
        self._by_name = {r.name: r for r in self.records}

    def __getitem__(self, name: str) -> Pose | None:
        return self._by_name[name].pose

    def __iter__(self) -> Iterator[str]:
        return (r.name for r in self.records)

    def __len__(self) -> int:
        return len(self.records)

    def record(self, name: str) -> Record:
        return self._by_name[name]


def _is_float(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _record_numbers(tokens: list[str]) -> bool:
    """An image name and 7 numbers, finite or not (a non-finite one makes a failed estimate, not junk)."""
    return len(tokens) >= 8 and tokens[0].lower().endswith(IMAGE_EXT) and all(_is_float(t) for t in tokens[1:8])


def _looks_like_record(tokens: list[str]) -> bool:
    """An image name and 7 finite numbers."""
    return _record_numbers(tokens) and all(math.isfinite(float(t)) for t in tokens[1:8])


_TENSOR_WORDS = re.compile(r"tensor\(|device='[^']*'|dtype=torch\.\w+|grad_fn=<\w+>|\bnan\b|\binf\b")
_TENSOR_CHARS = set("0123456789.,eE+-[]() \t\r")


def _is_tensor_fragment(line: str) -> bool:
    """Part of a printed torch tensor (what Marepo's test script spills after its records, wrapped)."""
    return set(_TENSOR_WORDS.sub("", line)) <= _TENSOR_CHARS


def _damaged_record(path: Path, line_no: int, tokens: list[str]) -> ValueError:
    """The error for a line that starts with an image name but does not hold a whole record."""
    if len(tokens) < 8:
        what = f"{len(tokens)} columns, a record has at least 8 (name qw qx qy qz tx ty tz)"
    else:
        bad = next(t for t in tokens[1:8] if not _is_float(t))
        what = f"not a number: {bad!r}"
    return ValueError(f"{path}:{line_no}: damaged pose record for {tokens[0]}: {what}")


def _make_pose(tokens: list[str], dialect: str = "hloc") -> Pose | None:
    vals = [float(t) for t in tokens[1:8]]
    try:
        if dialect == "cambridge":  # X Y Z = camera centre, then W P Q R
            q = Pose(vals[3:], [0.0, 0.0, 0.0])
            return Pose.from_centre(q.R, vals[:3])
        return Pose(vals[:4], vals[4:])
    except ValueError:
        return None


def _has_tensor_tail(tokens: list[str]) -> bool:
    """A Marepo record followed by its batch's error tensors: 8 pose tokens, then non-numeric text."""
    return len(tokens) > 8 and _record_numbers(tokens) and not _is_float(tokens[8])


def _stray_line(path: Path, line_no: int, line: str) -> ValueError:
    return ValueError(f"{path}:{line_no}: neither a pose record nor a printed tensor: {line.strip()[:60]!r}")


def detect_dialect(path: Path, lines: list[str]) -> str:
    """The dialect, decided by the record lines' token counts.

    Raw Marepo output (records followed by the reprs of the batch's error tensors, wrapped over several lines;
    CONVENTIONS §2) is recognised by its tensor tails and tensor lines; every record of such a file has 8 pose
    tokens. A line that is neither a record nor a printed tensor is an error naming it.
    """
    if lines and lines[0].strip().startswith(CAMBRIDGE_HEADER):
        return "cambridge"
    counts = set()
    junk = False
    for i, ln in enumerate(lines, 1):
        tok = ln.split()
        if not tok or tok[0].startswith("#"):
            continue
        if _has_tensor_tail(tok):
            counts.add(8)
            junk = True
        elif tok[0].lower().endswith(IMAGE_EXT) and not _record_numbers(tok):
            raise _damaged_record(path, i, tok)  # a truncated line is a lost query, not a Marepo tensor
        elif _looks_like_record(tok) or (len(tok) in (8, 9, 11) and tok[0].lower().endswith(IMAGE_EXT)):
            counts.add(len(tok))
        elif _is_tensor_fragment(ln):
            junk = True
        else:
            raise _stray_line(path, i, ln)
    if junk:
        if counts == {8}:
            return "marepo"
        raise ValueError(f"{path}: cannot detect the pose-file dialect (lines that are not pose records, "
                         f"record widths {sorted(counts)})")
    if counts == {11}:
        return "ace"
    if counts == {9}:
        return "pgt"
    if counts == {8}:
        return "hloc"
    if not counts:
        raise ValueError(f"{path}: no pose records found")
    raise ValueError(f"{path}: mixed record widths {sorted(counts)}; expected 8 (hloc), 9 (pgt) or 11 (ace)")


def read_text_poses(path, dialect: str = "auto") -> PoseFile:
    """Read a line-based pose file (``DIALECTS``; ``adapters.dialects.read_poses`` reads every format); raises
    ValueError naming file and line for a malformed line.

    Returns:
        A :class:`PoseFile` (ordered mapping name -> world-to-camera Pose, w x y z quaternions).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: pose file not found")
    text = path.read_bytes().decode("utf-8", errors="strict")  # not read_text: it would turn CRLF into LF
    bom = text.startswith("\ufeff")  # Windows editors' mark: not part of the first image name
    text = text.removeprefix("\ufeff")
    final_newline = text.endswith("\n")
    lines = text.split("\n")
    if final_newline:
        lines = lines[:-1]
    if dialect == "auto":
        dialect = detect_dialect(path, lines)
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r}; choose from {DIALECTS}")
    width = COLUMNS[dialect]
    records, seen, unusable = [], {}, []
    for i, ln in enumerate(lines, 1):
        tok = ln.split()
        if not tok or tok[0].startswith("#") or (dialect == "cambridge" and i <= 3):
            continue
        if dialect == "marepo":
            if not _record_numbers(tok):
                if tok[0].lower().endswith(IMAGE_EXT):
                    raise _damaged_record(path, i, tok)
                if not _is_tensor_fragment(ln):
                    raise _stray_line(path, i, ln)
                continue  # wrapped error tensors: not a record (CONVENTIONS §2, robust parse)
        else:
            if len(tok) != width:
                raise ValueError(f"{path}:{i}: expected {width} columns ({dialect}), got {len(tok)}")
            bad = [t for t in tok[1:] if not _is_float(t)]
            if bad:
                raise ValueError(f"{path}:{i}: not a number: {bad[0]!r}")
        if tok[0] in seen:
            raise ValueError(f"{path}:{i}: image {tok[0]!r} appears twice (first at line {seen[tok[0]]})")
        seen[tok[0]] = i
        pose = _make_pose(tok, dialect)
        if pose is None:
            unusable.append((i, tok[0]))
        records.append(Record(i, ln, tok[0], pose, tok))
    if not records:
        raise ValueError(f"{path}: no pose records found")
    if unusable:  # one warning for the cause, however many lines
        i, name = unusable[0]
        logger.warning("%s:%d: %d unusable pose%s (non-finite value or zero quaternion; first: %s) kept as failed "
                       "estimates", path, i, len(unusable), "" if len(unusable) == 1 else "s", name)
    return PoseFile(path, dialect, lines, records, final_newline, bom)


def format_pose_tokens(pose: Pose, dialect: str = "hloc") -> list[str]:
    """qw qx qy qz tx ty tz (Cambridge: X Y Z qw qx qy qz) as shortest round-trip decimal strings."""
    vals = (list(pose.centre()) + list(pose.qvec)) if dialect == "cambridge" else list(pose.as_array())
    return [repr(float(v)) for v in vals]


def write_text_poses(path, poses: Mapping[str, Pose], like: PoseFile) -> Path:
    """Write ``like``'s file with the poses in ``poses`` replaced; everything else is copied verbatim.

    The columns, line order, name strings and extra columns (ACE errors, pGT focal) stay as in the input; a
    line whose pose is unchanged (or absent from ``poses``) is written byte for byte. Atomic; never writes over
    the input file.
    """
    path = Path(path)
    if path.exists() and like.path.exists() and path.resolve() == like.path.resolve():
        raise ValueError(f"{path}: refusing to overwrite the input pose file")
    by_line = {r.line_no: r for r in like.records}
    out = []
    for i, ln in enumerate(like.lines, 1):
        r = by_line.get(i)
        if r is not None and r.name in poses and poses[r.name] is not None and poses[r.name] != r.pose:
            new = " ".join([r.name] + format_pose_tokens(poses[r.name], like.dialect) + r.tokens[8:])
            out.append(new + "\r" if ln.endswith("\r") else new)  # CRLF files stay CRLF
        else:
            out.append(ln)
    text = ("\ufeff" if like.bom else "") + "\n".join(out) + ("\n" if like.final_newline else "")
    atomic_write_bytes(path, text.encode("utf-8"))
    return path
