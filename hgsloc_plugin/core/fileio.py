"""Safe output, for every file the package writes: atomic writes (temporary file + rename) with the mode the
process's umask gives, and strict JSON (non-finite numbers as null)."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path


def current_umask() -> int:
    """The process's file-mode creation mask (read without changing it for long)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write ``payload`` to ``path`` through a temporary file in the same folder and a rename; the file's mode is
    what a plain ``open`` would give (0o666 less the umask: 0644 under umask 022), not the temporary file's 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def json_safe(value):
    """``value`` with every non-finite float replaced by None (JSON has no NaN or Infinity)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:  # numpy scalar
        return json_safe(value.item())
    return value


def dumps_json(value, indent: int | None = 1) -> str:
    """Strict JSON text of ``value`` (non-finite numbers become null)."""
    return json.dumps(json_safe(value), indent=indent, allow_nan=False)


def write_json(path: Path, value) -> None:
    """Atomically write ``value`` as strict JSON."""
    atomic_write_bytes(path, dumps_json(value).encode())
