"""HLoc's files: results (8 columns ``name qw qx qy qz tx ty tz``) and the query list with intrinsics.

The refinement step that runs on them is :mod:`hgsloc_plugin.hloc_step` (``python -m hgsloc_plugin.hloc_step``).
"""

from __future__ import annotations

from pathlib import Path

from .dialects import read_poses as _read
from .dialects import write_poses
from .intrinsics import from_query_list, parse_query_list
from .posefile import PoseFile

__all__ = ["from_query_list", "inlier_log_path", "parse_query_list", "read_inlier_log", "read_poses", "write_poses"]


def read_poses(path) -> PoseFile:
    """An hloc results file (``name qw qx qy qz tx ty tz``, world-to-camera)."""
    return _read(path, "hloc")


#: modules whose classes an hloc log may rebuild: containers, paths and numpy arrays; anything else (pycolmap's
#: pose objects, ...) is read as an inert placeholder, so loading a log never runs code from another package
_LOG_MODULES = {"builtins": {"dict", "list", "tuple", "set", "frozenset", "int", "float", "str", "bytes", "bool",
                             "complex", "slice", "range"},
                "collections": {"OrderedDict", "defaultdict"},
                "pathlib": {"Path", "PosixPath", "WindowsPath", "PurePath", "PurePosixPath", "PureWindowsPath"},
                "numpy": {"ndarray", "dtype"},
                "numpy.core.multiarray": {"_reconstruct", "scalar"},
                "numpy._core.multiarray": {"_reconstruct", "scalar"}}


class _Placeholder:
    """What a log's object of another package (e.g. a pycolmap ``Rigid3d``) is read as: it keeps nothing."""

    def __init__(self, *args, **kwargs):
        pass

    def __setstate__(self, state):
        pass


def inlier_log_path(results) -> Path:
    """Where hloc's ``localize_sfm`` writes its log for ``results``: ``<results>_logs.pkl`` beside it."""
    results = Path(results)
    return results.with_name(results.name + "_logs.pkl")


def read_inlier_log(results) -> dict[str, float] | None:
    """hloc's PnP inlier count per query, from the log beside its ``results`` file (``<results>_logs.pkl``:
    ``logs["loc"][name]["PnP_ret"]["num_inliers"]``).

    Returns:
        name -> count (queries hloc failed to localize, without a count, are left out), or None when there is no
        log. Raises ValueError naming the file when it is there but unreadable or not an hloc log.
    """
    import pickle

    path = inlier_log_path(results)
    if not path.exists():
        return None

    class _Restricted(pickle.Unpickler):
        def find_class(self, module, name):
            if name in _LOG_MODULES.get(module, ()):
                return super().find_class(module, name)
            return _Placeholder

    try:
        with open(path, "rb") as f:
            logs = _Restricted(f).load()
        loc = logs["loc"]
        if not isinstance(loc, dict):
            raise TypeError(f"'loc' is a {type(loc).__name__}")
    except Exception as exc:  # any malformed pickle: the caller warns and goes on without counts
        raise ValueError(f"{path}: not a readable hloc log ({type(exc).__name__}: {exc})") from exc
    out = {}
    for name, entry in loc.items():
        try:
            n = float(entry["PnP_ret"]["num_inliers"])
        except (KeyError, TypeError, ValueError):
            continue
        if n == n:  # not nan
            out[str(name)] = n
    return out
