"""A trained 3D Gaussian Splatting scene and its official (graphdeco) PLY layout."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .fileio import atomic_write_bytes

logger = logging.getLogger("hgsloc_plugin")

SH_C0 = 0.28209479177387814
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
_REST_TO_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
              "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4"}


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def resolve_scene(path) -> tuple[Path, bool | None]:
    """A ``.ply`` path, or a 3DGS trainer's output folder (Inria layout: ``cfg_args`` with
    ``white_background=True|False``, ``point_cloud/iteration_<N>/point_cloud.ply``)
    -> (the latest iteration's ply, white_background or None).

    ``white_background`` is None when the folder has no ``cfg_args`` (or for a plain ``.ply``).
    """
    path = Path(path)
    if not path.is_dir():
        return path, None
    its = []
    for p in (path / "point_cloud").glob("iteration_*/point_cloud.ply"):
        m = re.fullmatch(r"iteration_(\d+)", p.parent.name)
        if m:
            its.append((int(m.group(1)), p))
    if not its:
        raise FileNotFoundError(f"{path}: no point_cloud/iteration_*/point_cloud.ply in this folder "
                                "(give a 3DGS .ply or a trainer's output folder)")
    it, ply = max(its)
    white = None
    cfg = path / "cfg_args"
    if cfg.is_file():
        m = re.search(r"white_background\s*=\s*(True|False)", cfg.read_text(errors="replace"))
        if m:
            white = m.group(1) == "True"
    logger.info("scene %s: iteration %d (%s), background %s", path, it, ply,
                "white" if white else "black" if white is not None else "not recorded (black)")
    return ply, white



@dataclass(eq=False)
class GaussianScene:
    """Activated 3DGS parameters (float32), plus the raw file values for an exact round trip.

    Attributes:
        means: centres in world coordinates [N, 3].
        quats: unit rotations w, x, y, z [N, 4].
        scales: standard deviations along the local axes [N, 3] (exp of the file's ``scale_i``).
        opacities: in (0, 1) [N] (sigmoid of the file's ``opacity``).
        sh: spherical-harmonic colour coefficients [N, K, 3], K = (degree + 1)^2; sh[:, 0] is the DC term.
        raw: the file's values per property name (float32 [N] each), used by :meth:`to_ply`.
        source: the path it was read from, if any.
        white_background: what the trainer recorded (``cfg_args``) when read from its output folder, else None.
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    raw: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    source: str | None = None
    white_background: bool | None = None

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    # construction
    @classmethod
    def from_arrays(cls, means, quats, scales, opacities, sh=None, colors=None, *, source: str | None = None,
                    ) -> GaussianScene:
        """Build from activated arrays.

        Args:
            means: [N, 3]; quats: [N, 4] w, x, y, z (normalised here); scales: [N, 3] (> 0);
            opacities: [N] in (0, 1); sh: [N, K, 3] with K in {1, 4, 9, 16}, or colors: [N, 3] RGB in [0, 1]
            (converted to a degree-0 SH DC term). Torch tensors are accepted.
        """
        def arr(x, name, shape_tail):
            a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float32)
            if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != shape_tail:
                raise ValueError(f"{name} must be [N, {', '.join(map(str, shape_tail))}], got {tuple(a.shape)}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} has non-finite values")
            return np.ascontiguousarray(a)

        means = arr(means, "means", (3,))
        n = means.shape[0]
        quats = arr(quats, "quats", (4,))
        scales = arr(scales, "scales", (3,))
        opac = np.asarray(opacities.detach().cpu().numpy() if hasattr(opacities, "detach") else opacities,
                          dtype=np.float32).reshape(-1)
        if sh is None:
            if colors is None:
                raise ValueError("give sh [N, K, 3] or colors [N, 3]")
            colors = arr(colors, "colors", (3,))
            sh = ((colors - 0.5) / SH_C0)[:, None, :]
        sh = np.asarray(sh.detach().cpu().numpy() if hasattr(sh, "detach") else sh, dtype=np.float32)
        if sh.ndim != 3 or sh.shape[2] != 3 or sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh must be [N, K, 3] with K in (1, 4, 9, 16), got {tuple(sh.shape)}")
        for name, a in (("quats", quats), ("scales", scales), ("opacities", opac), ("sh", sh)):
            if a.shape[0] != n:
                raise ValueError(f"{name} has {a.shape[0]} rows, means has {n}")
        if not np.all(np.isfinite(opac)) or not np.all(np.isfinite(sh)):
            raise ValueError("opacities / sh have non-finite values")
        if np.any(scales <= 0):
            raise ValueError("scales must be positive (activated values, not log-scales)")
        if np.any((opac <= 0) | (opac >= 1)):
            raise ValueError("opacities must lie in (0, 1) (activated values, not logits)")
        qn = np.linalg.norm(quats, axis=1)
        if np.any(qn < 1e-12):
            raise ValueError(f"{int(np.sum(qn < 1e-12))} quaternions have zero norm")
        k = sh.shape[1] - 1
        raw = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
        raw.update({"nx": np.zeros(n, np.float32), "ny": np.zeros(n, np.float32), "nz": np.zeros(n, np.float32)})
        for c in range(3):
            raw[f"f_dc_{c}"] = sh[:, 0, c]
        for c in range(3):
            for j in range(k):
                raw[f"f_rest_{c * k + j}"] = sh[:, 1 + j, c]
        raw["opacity"] = np.log(opac / (1 - opac)).astype(np.float32)
        for i in range(3):
            raw[f"scale_{i}"] = np.log(scales[:, i]).astype(np.float32)
        for i in range(4):
            raw[f"rot_{i}"] = quats[:, i]
        raw = {key: np.ascontiguousarray(v, dtype=np.float32) for key, v in raw.items()}
        return cls._from_raw(raw, source)

    @classmethod
    def _from_raw(cls, raw: dict[str, np.ndarray], source: str | None) -> GaussianScene:
        where = source or "<arrays>"
        n_rest = sum(1 for k in raw if k.startswith("f_rest_"))
        if n_rest not in _REST_TO_DEGREE:
            raise ValueError(f"{where}: {n_rest} f_rest_* properties do not match an SH degree "
                             "(expected 0, 9, 24 or 45)")
        missing_rest = [f"f_rest_{i}" for i in range(n_rest) if f"f_rest_{i}" not in raw]
        if missing_rest:
            raise ValueError(f"{where}: f_rest properties are not numbered 0..{n_rest - 1} (missing {missing_rest[0]})")
        for key in _REQUIRED + [f"f_rest_{i}" for i in range(n_rest)]:
            bad = ~np.isfinite(raw[key])
            if bad.any():
                raise ValueError(f"{where}: property {key!r} has {int(bad.sum())} non-finite values "
                                 f"(first at vertex {int(np.argmax(bad))})")
        means = np.stack([raw["x"], raw["y"], raw["z"]], 1).astype(np.float32)
        q = np.stack([raw[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
        qn = np.linalg.norm(q, axis=1)
        if np.any(qn < 1e-12):
            raise ValueError(f"{where}: {int(np.sum(qn < 1e-12))} Gaussians have a zero rotation quaternion "
                             f"(first at vertex {int(np.argmax(qn < 1e-12))})")
        quats = (q / qn[:, None]).astype(np.float32)
        scales = np.exp(np.stack([raw[f"scale_{i}"] for i in range(3)], 1).astype(np.float64)).astype(np.float32)
        if not np.all(np.isfinite(scales)):
            raise ValueError(f"{where}: exp(scale) overflows (scale_* values too large)")
        opac = _sigmoid(raw["opacity"].astype(np.float64)).astype(np.float32)
        m = n_rest // 3
        dc = np.stack([raw[f"f_dc_{c}"] for c in range(3)], 1)[:, None, :]
        if m:
            rest = np.stack([raw[f"f_rest_{i}"] for i in range(n_rest)], 1).reshape(-1, 3, m).transpose(0, 2, 1)
            sh = np.concatenate([dc, rest], 1)
        else:
            sh = dc
        return cls(np.ascontiguousarray(means), np.ascontiguousarray(quats), np.ascontiguousarray(scales),
                   np.ascontiguousarray(opac), np.ascontiguousarray(sh, dtype=np.float32), raw, source)

    @classmethod
    def from_ply(cls, path) -> GaussianScene:
        """Read an official-layout 3DGS PLY (binary little-endian), or the latest iteration's PLY of a trainer's
        output folder (see :func:`resolve_scene`); raises ValueError naming the file and problem."""
        path, white = resolve_scene(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: scene file not found")
        data = path.read_bytes()
        raw = _parse_ply(data, str(path))
        scene = cls._from_raw(raw, str(path))
        scene.white_background = white
        return scene

    def to_ply(self, path) -> Path:
        """Write the official layout (same properties and order as read), atomically."""
        path = Path(path)
        names = list(self.raw.keys())
        n = self.num_gaussians
        header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
        header += [f"property float {k}" for k in names]
        header.append("end_header")
        body = np.empty((n, len(names)), dtype="<f4")
        for j, k in enumerate(names):
            body[:, j] = self.raw[k]
        payload = ("\n".join(header) + "\n").encode("ascii") + body.tobytes()
        atomic_write_bytes(path, payload)
        return path

    def digest(self) -> str:
        """A SHA-256 (hex) of what renders: the activated means, rotations, scales, opacities and SH coefficients,
        with their shapes; equal for the same map read from any file or path."""
        import hashlib

        h = hashlib.sha256()
        for a in (self.means, self.quats, self.scales, self.opacities, self.sh):
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(memoryview(a).cast("B"))
        return h.hexdigest()

    # geometry helpers
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Robust bounding box (1st and 99th percentile of the means): (lo [3], hi [3])."""
        return np.percentile(self.means, 1, axis=0), np.percentile(self.means, 99, axis=0)

    def extent(self) -> float:
        """Diagonal of the robust bounding box."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))


def _parse_ply(data: bytes, where: str) -> dict[str, np.ndarray]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{where}: not a PLY file (no 'ply' magic or no 'end_header')")
    nl = data.find(b"\n", end)
    if nl < 0:
        raise ValueError(f"{where}: header is not terminated by a newline")
    try:
        header = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{where}: header is not ASCII") from exc
    body = data[nl + 1:]
    fmt, elements, current = None, [], None
    for ln, line in enumerate(header, 1):
        tok = line.split()
        if not tok or tok[0] in ("ply", "comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1] if len(tok) > 1 else ""
        elif tok[0] == "element":
            if len(tok) != 3:
                raise ValueError(f"{where}: header line {ln}: malformed element line {line!r}")
            current = {"name": tok[1], "count": int(tok[2]), "props": []}
            elements.append(current)
        elif tok[0] == "property":
            if current is None:
                raise ValueError(f"{where}: header line {ln}: property before any element")
            if tok[1] == "list":
                raise ValueError(f"{where}: header line {ln}: list property {tok[-1]!r} is not a 3DGS layout")
            if tok[1] not in _PLY_TYPES:
                raise ValueError(f"{where}: header line {ln}: unknown property type {tok[1]!r}")
            current["props"].append((tok[2], _PLY_TYPES[tok[1]]))
    if fmt != "binary_little_endian":
        raise ValueError(f"{where}: format is {fmt!r}; 3DGS scenes must be binary_little_endian")
    if not elements or elements[0]["name"] != "vertex":
        raise ValueError(f"{where}: the first element must be 'vertex'")
    vertex = elements[0]
    names = [p for p, _ in vertex["props"]]
    missing = [k for k in _REQUIRED if k not in names]
    if missing:
        raise ValueError(f"{where}: missing properties {missing}")
    if len(set(names)) != len(names):
        raise ValueError(f"{where}: duplicated property names")
    dtype = np.dtype([(p, t) for p, t in vertex["props"]])
    n = vertex["count"]
    need = n * dtype.itemsize
    if len(body) < need:
        raise ValueError(f"{where}: truncated: {n} vertices need {need} bytes of data, file has {len(body)}")
    arr = np.frombuffer(body[:need], dtype=dtype, count=n)
    return {p: np.ascontiguousarray(arr[p], dtype=np.float32) for p in names if not _is_int(dtype[p])}


def _is_int(dt: np.dtype) -> bool:
    return dt.kind in "iu"
