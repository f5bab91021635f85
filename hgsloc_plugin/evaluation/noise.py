"""Coarse-pose noise protocols: the paper's ``qA,tB`` and exact-magnitude SE(3) noise."""

from __future__ import annotations

import math

import numpy as np

from ..core.pose import Pose, so3_exp


def qt_noise(T_cam_world: Pose, A: int, B: int, rng: np.random.Generator) -> Pose:
    """The paper's protocol: each raw q component += k * 10^-A, each t component += k * 10^-B.

    k is an integer drawn uniformly from -9..9 per component (seeded by ``rng``); the quaternion is then
    normalised (the official files keep it unnormalised).
    """
    q, t = qt_noise_raw(T_cam_world, A, B, rng)
    return Pose(q, t)


def qt_noise_raw(T_cam_world: Pose, A: int, B: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The un-normalised (q [4], t [3]) of :func:`qt_noise` (what the paper's files hold)."""
    kq = rng.integers(-9, 10, size=4)
    kt = rng.integers(-9, 10, size=3)
    return T_cam_world.qvec + kq * 10.0 ** (-A), T_cam_world.tvec + kt * 10.0 ** (-B)


def se3_noise(T_cam_world: Pose, rot_deg: float, trans: float, rng: np.random.Generator) -> Pose:
    """Rotate the camera by exactly ``rot_deg`` about a random axis (about its centre) and move its centre by
    exactly ``trans`` (scene units) in a random direction."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    R = so3_exp(axis * math.radians(rot_deg)) @ T_cam_world.R
    c = T_cam_world.centre() + d * trans
    return Pose.from_centre(R, c)


def parse_protocol(spec: str) -> tuple[str, float, float]:
    """Parse "q2,t1" / "q2_t1" (paper), "3cm,1deg" / "0.03m,1deg" (SE(3), scene units) or "2%,1deg" (SE(3), a
    share of the query's median depth) -> (kind, a, b).

    Returns ("qt", A, B), ("se3", scene units, degrees) or ("depth", fraction of the depth, degrees).
    """
    s = spec.strip().lower().replace("_", ",").replace(" ", "")
    parts = s.split(",")
    usage = f"noise spec {spec!r}: expected 'qA,tB', 'Dcm,Rdeg' or 'P%,Rdeg'"
    if len(parts) != 2:
        raise ValueError(usage)
    try:
        if parts[0].startswith("q") and parts[1].startswith("t"):
            return "qt", int(parts[0][1:]), int(parts[1][1:])
        t_part = next((p for p in parts if p.endswith(("cm", "m", "%"))), None)
        r_part = next((p for p in parts if p.endswith("deg")), None)
        if t_part is None or r_part is None:
            raise ValueError(usage)
        deg = float(r_part[:-3])
        if t_part.endswith("%"):
            return "depth", float(t_part[:-1]) / 100, deg
        return "se3", float(t_part[:-2]) / 100 if t_part.endswith("cm") else float(t_part[:-1]), deg
    except ValueError as exc:
        raise ValueError(usage) from exc


def apply_protocol(T_cam_world: Pose, spec: str, rng: np.random.Generator, depth: float | None = None) -> Pose:
    """Perturb a pose by the protocol named by ``spec`` (see :func:`parse_protocol`); a share of the depth needs
    the query's median ``depth`` (scene units)."""
    kind, a, b = parse_protocol(spec)
    if kind == "qt":
        return qt_noise(T_cam_world, int(a), int(b), rng)
    if kind == "depth":
        if depth is None:
            raise ValueError(f"noise spec {spec!r} is a share of the query's median depth: give the depth")
        return se3_noise(T_cam_world, b, a * depth, rng)
    return se3_noise(T_cam_world, b, a, rng)
