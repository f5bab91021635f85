"""World-to-camera rigid poses (COLMAP / pycolmap ``cam_from_world`` convention)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def qvec_to_rotmat(q) -> np.ndarray:
    """Unit quaternion (w, x, y, z) [4] -> rotation matrix [3, 3] float64 (Hamilton convention); the numbers of
    :func:`qvecs_to_rotmats`, bit for bit (the same float64 operations, on Python floats: a pose makes one)."""
    w, x, y, z = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ], dtype=np.float64)


def qvecs_to_rotmats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) [N, 4] -> rotation matrices [N, 3, 3] float64 (Hamilton convention)."""
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion (w, x, y, z) [4] with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def so3_exp(w) -> np.ndarray:
    """Axis-angle vector [3] (radians) -> rotation matrix [3, 3] (Rodrigues, exact at 0)."""
    w = np.asarray(w, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=np.float64)
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(theta) / theta * K + (1 - math.cos(theta)) / theta**2 * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> axis-angle vector [3] (radians), the inverse of :func:`so3_exp` for angles below pi
    (through the unit quaternion, so stable near 0)."""
    q = rotmat_to_qvec(R)  # w >= 0
    s = float(np.linalg.norm(q[1:]))
    if s < 1e-300:
        return np.zeros(3)
    return q[1:] / s * (2.0 * math.atan2(s, q[0]))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations in degrees, stable for small angles (CONVENTIONS §7)."""
    Rd = np.asarray(R_a, np.float64).T @ np.asarray(R_b, np.float64)
    v = np.array([Rd[2, 1] - Rd[1, 2], Rd[0, 2] - Rd[2, 0], Rd[1, 0] - Rd[0, 1]])
    return math.degrees(math.atan2(np.linalg.norm(v) / 2, (np.trace(Rd) - 1) / 2))


@dataclass(frozen=True, eq=False)
class Pose:
    """World-to-camera pose: ``p_cam = R @ p_world + t``.

    Convention: quaternion Hamilton (w, x, y, z), normalised on construction and stored with w >= 0; float64.
    Camera axes are OpenCV (x right, y down, z forward). Use names like ``T_cam_world`` for instances.

    Example:
        >>> T = Pose([1, 0, 0, 0], [0, 0, 1])
        >>> T.centre()
        array([ 0.,  0., -1.])
    """

    qvec: np.ndarray  # [4] w, x, y, z
    tvec: np.ndarray  # [3]

    def __init__(self, qvec, tvec):
        q = np.asarray(qvec, dtype=np.float64).reshape(-1)
        t = np.asarray(tvec, dtype=np.float64).reshape(-1)
        if q.shape != (4,):
            raise ValueError(f"qvec must have 4 values (w, x, y, z), got shape {q.shape}")
        if t.shape != (3,):
            raise ValueError(f"tvec must have 3 values, got shape {t.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
            raise ValueError(f"pose has non-finite values: q={q.tolist()}, t={t.tolist()}")
        n = float(np.linalg.norm(q))
        if n < 1e-12:
            raise ValueError(f"pose quaternion has zero norm: q={q.tolist()}")
        q = q / n
        if q[0] < 0:
            q = -q
        q.flags.writeable = False
        t = t.copy()
        t.flags.writeable = False
        object.__setattr__(self, "qvec", q)
        object.__setattr__(self, "tvec", t)

    # constructors
    @classmethod
    def from_stored(cls, qvec, tvec) -> Pose:
        """A pose from the ``qvec`` / ``tvec`` of a pose made earlier (a report's record): kept bit for bit where
        the quaternion is already unit with w >= 0 (the constructor's division would move its last bits), else
        normalised as by the constructor."""
        pose = cls(qvec, tvec)
        q = np.asarray(qvec, dtype=np.float64).reshape(-1)
        if q[0] >= 0 and abs(float(np.linalg.norm(q)) - 1.0) < 1e-12:
            q = q.copy()
            q.flags.writeable = False
            object.__setattr__(pose, "qvec", q)
        return pose

    @classmethod
    def identity(cls) -> Pose:
        return cls([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0])

    @classmethod
    def from_Rt(cls, R, t) -> Pose:
        """From a rotation matrix [3, 3] and translation [3] (world-to-camera)."""
        R = np.asarray(R, dtype=np.float64)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise ValueError(f"R must be a finite [3, 3] matrix, got shape {R.shape}")
        if abs(np.linalg.det(R) - 1) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
            raise ValueError("R is not a proper rotation matrix (det 1, orthonormal)")
        return cls(rotmat_to_qvec(R), t)

    @classmethod
    def from_matrix(cls, M) -> Pose:
        """From a world-to-camera matrix [3, 4] or [4, 4]."""
        M = np.asarray(M, dtype=np.float64)
        if M.shape not in ((3, 4), (4, 4)):
            raise ValueError(f"pose matrix must be [3, 4] or [4, 4], got {M.shape}")
        return cls.from_Rt(M[:3, :3], M[:3, 3])

    @classmethod
    def from_centre(cls, R, centre) -> Pose:
        """From a world-to-camera rotation [3, 3] and a camera centre [3] in world coordinates."""
        R = np.asarray(R, dtype=np.float64)
        return cls.from_Rt(R, -R @ np.asarray(centre, dtype=np.float64))

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 0.0, 1.0)) -> Pose:
        """Camera at ``eye`` looking at ``target`` with image-up close to ``up`` (OpenCV axes)."""
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:
            x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return cls.from_centre(np.stack([x, y, z]), eye)

    @classmethod
    def from_pycolmap(cls, rigid) -> Pose:
        """From a ``pycolmap.Rigid3d`` (cam_from_world); pycolmap stores quaternions as x, y, z, w."""
        xyzw = np.asarray(rigid.rotation.quat, dtype=np.float64)
        return cls(xyzw[[3, 0, 1, 2]], np.asarray(rigid.translation, dtype=np.float64))

    # conversions
    def to_pycolmap(self):
        """As a ``pycolmap.Rigid3d`` (cam_from_world)."""
        import pycolmap

        return pycolmap.Rigid3d(pycolmap.Rotation3d(self.qvec[[1, 2, 3, 0]]), self.tvec.copy())

    @property
    def R(self) -> np.ndarray:
        """Rotation world-to-camera [3, 3] (a copy: the pose keeps its own)."""
        return self._rot().copy()

    def _rot(self) -> np.ndarray:
        """The rotation [3, 3], read-only, computed from ``qvec`` once per pose (rotations are read far more often
        than poses are made: composing, inverting and comparing poses all read them)."""
        R = self.__dict__.get("_R")
        if R is None:
            R = qvec_to_rotmat(self.qvec)
            R.flags.writeable = False
            object.__setattr__(self, "_R", R)
        return R

    @property
    def t(self) -> np.ndarray:
        """Translation [3]."""
        return np.array(self.tvec)

    def matrix(self) -> np.ndarray:
        """World-to-camera matrix [4, 4]."""
        M = np.eye(4)
        M[:3, :3] = self._rot()
        M[:3, 3] = self.tvec
        return M

    def matrix34(self) -> np.ndarray:
        """World-to-camera matrix [3, 4]."""
        return self.matrix()[:3]

    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates [3]: c = -R^T t."""
        return -self._rot().T @ self.tvec

    def inv(self) -> Pose:
        """The inverse transform (camera-to-world)."""
        R = self._rot()
        return Pose.from_Rt(R.T, -R.T @ self.tvec)

    def __matmul__(self, other: Pose) -> Pose:
        """Composition: (A @ B)(p) = A(B(p))."""
        R = self._rot() @ other._rot()
        return Pose(rotmat_to_qvec(R), self._rot() @ other.tvec + self.tvec)

    def perturbed_in_camera(self, rot_vec, trans) -> Pose:
        """Left-multiply by a camera-frame motion: rotation about the camera axes [3] (rad), then translation [3]."""
        dR = so3_exp(rot_vec)
        return Pose(rotmat_to_qvec(dR @ self._rot()), dR @ self.tvec + np.asarray(trans, dtype=np.float64))

    def offset_in_camera(self, other: Pose) -> np.ndarray:
        """The camera-frame motion [6] = (rotation vector [3] rad, translation [3]) that takes this pose to ``other``:
        ``self.perturbed_in_camera(xi[:3], xi[3:]) == other`` (the inverse of :meth:`perturbed_in_camera`)."""
        dR = other._rot() @ self._rot().T
        return np.concatenate([so3_log(dR), other.tvec - dR @ self.tvec])

    def errors_to(self, other: Pose) -> tuple[float, float]:
        """(camera-centre distance, rotation angle in degrees) between this pose and ``other``."""
        return float(np.linalg.norm(self.centre() - other.centre())), rotation_angle_deg(other._rot(), self._rot())

    def as_array(self) -> np.ndarray:
        """[7] = qw qx qy qz tx ty tz."""
        return np.concatenate([self.qvec, self.tvec])

    def __eq__(self, other) -> bool:
        return isinstance(other, Pose) and np.array_equal(self.qvec, other.qvec) and np.array_equal(
            self.tvec, other.tvec)

    def __hash__(self) -> int:
        return hash((self.qvec.tobytes(), self.tvec.tobytes()))

    def __repr__(self) -> str:
        q = " ".join(f"{v:.6g}" for v in self.qvec)
        t = " ".join(f"{v:.6g}" for v in self.tvec)
        return f"Pose(q=[{q}], t=[{t}])"
