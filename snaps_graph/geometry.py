"""Small SO(3)/SE(3) helpers on numpy matrices (poses are 4x4 T_world_cam, KITTI camera axes):
the package's one module of rotation maths.

Quaternion to matrix, slerp, rotation vectors and angles go through ``scipy.spatial.transform``
(imported on first use: it costs seconds to import on a busy machine). Where scipy would change
the bits of the poses a run writes, the closed forms stay (docs/decisions.md, "Dependencies"):
the Rodrigues exponential and logarithm the estimators compose poses with (scipy's agree to
1e-15, not to the last bit) and the matrix-to-quaternion of the TUM writer.
"""

from __future__ import annotations

import numpy as np

from .errors import SnapsGraphError


def yaw_deg(R: np.ndarray) -> float | np.ndarray:
    """Heading about the camera's vertical axis: atan2(R[0,2], R[2,2]) of R_world_cam, degrees.

    Accepts one 3x3 (or 4x4) matrix or a stack (N, 3|4, 3|4).
    """
    R = np.asarray(R)
    return np.degrees(np.arctan2(R[..., 0, 2], R[..., 2, 2]))


def wrap_deg(angle: float | np.ndarray) -> float | np.ndarray:
    """Wrap degrees to (-180, 180]."""
    a = np.mod(np.asarray(angle, dtype=float) + 180.0, 360.0) - 180.0
    a = np.where(a == -180.0, 180.0, a)
    return a if a.ndim else float(a)


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4x4)."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def hat(w: np.ndarray) -> np.ndarray:
    """The skew matrix [w]x (hat(w) @ v = w x v)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues); first order below 1e-12 rad."""
    th = float(np.linalg.norm(w))
    W = hat(w)
    if th < 1e-12:
        return np.eye(3) + W
    return np.eye(3) + np.sin(th) / th * W + (1 - np.cos(th)) / th**2 * (W @ W)


def exp_so3_scaled(rotvec: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Rodrigues, batched along one axis: (len(scales), 3, 3) rotations Exp(scale·rotvec)."""
    theta = float(np.linalg.norm(rotvec))
    out = np.broadcast_to(np.eye(3), (len(scales), 3, 3)).copy()
    if theta == 0.0:
        return out
    k = rotvec / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.asarray(scales, float) * theta
    out += np.sin(t)[:, None, None] * K + (1.0 - np.cos(t))[:, None, None] * (K @ K)
    return out


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, radians) of a rotation matrix; not unique near 180°."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * (0.5 if th < 1e-8 else th / (2.0 * np.sin(th)))


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(qx, qy, qz, qw) of a rotation matrix, qw >= 0 (Shepperd's method).

    Not scipy's: for a matrix that is not quite a rotation (a pose file's 7 digits, a chain of
    them) the two read different entries and part by up to 1e-5, which would change the TUM
    files a run writes; for a true rotation they agree to 2e-16."""
    R = np.asarray(R, float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        w = 0.25 * s
        x = (R[2, 1] - R[1, 2]) / s
        y = (R[0, 2] - R[2, 0]) / s
        z = (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        w = (R[2, 1] - R[1, 2]) / s
        x = 0.25 * s
        y = (R[0, 1] + R[1, 0]) / s
        z = (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        w = (R[0, 2] - R[2, 0]) / s
        x = (R[0, 1] + R[1, 0]) / s
        y = 0.25 * s
        z = (R[1, 2] + R[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        w = (R[1, 0] - R[0, 1]) / s
        x = (R[0, 2] + R[2, 0]) / s
        y = (R[1, 2] + R[2, 1]) / s
        z = 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_to_rotation(q: np.ndarray | list[float]) -> np.ndarray:
    """Rotation matrix of (qx, qy, qz, qw) (normalised first), or a stack of them."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, float)).as_matrix()


def slerp(q0: np.ndarray, q1: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) the fractions ``a`` (N,) of the way from ``q0`` to ``q1`` (N, 4)
    (qx, qy, qz, qw) along the shorter arc: R0 Exp(a Log(R0^T R1))."""
    from scipy.spatial.transform import Rotation

    r0 = Rotation.from_quat(np.asarray(q0, float))
    arc = (r0.inv() * Rotation.from_quat(np.asarray(q1, float))).as_rotvec()
    return (r0 * Rotation.from_rotvec(np.asarray(a, float)[:, None] * arc)).as_matrix()


def rotvecs_to_matrices(rotvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3) (axis times angle, radians)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvecs, float)).as_matrix()


def matrices_to_rotvecs(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3); angles in [0, pi]."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, float)).as_rotvec()


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """Angles (radians, [0, pi]) of a stack of rotation matrices (N, 3, 3), accurate near 0 and pi."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, float)).magnitude()


def adjoint(T: np.ndarray) -> np.ndarray:
    """SE(3) adjoint of T = [R, t] for [rotation, translation] twists: exp(Ad xi) T = T exp(xi)."""
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3], Ad[3:, 3:], Ad[3:, :3] = R, R, hat(t) @ R
    return Ad


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """V(w) of SE(3)'s exponential: t = V(w) u for the twist (w, u)."""
    th = float(np.linalg.norm(w))
    W = hat(w)
    if th < 1e-8:
        return np.eye(3) + 0.5 * W
    return np.eye(3) + (1.0 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * (W @ W)


def scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """T**s for a rigid motion T (4x4): the twist log(T) scaled by ``s`` then exponentiated, so
    a constant-velocity step over one interval predicts the step over ``s`` intervals
    (``scale_motion(T, 2) == T @ T``). Rotations near 180 degrees (no unique log) and
    non-finite input give the identity."""
    T = np.asarray(T, np.float64)
    if not np.all(np.isfinite(T)) or not np.isfinite(s):
        return np.eye(4)
    R = T[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    if th > np.pi - 1e-3:
        return np.eye(4)
    w = log_so3(R)
    u = np.linalg.solve(_left_jacobian(w), T[:3, 3])
    ws = s * w
    out = np.eye(4)
    out[:3, :3] = exp_so3(ws)
    out[:3, 3] = _left_jacobian(ws) @ (s * u)
    return out


def umeyama_alignment(src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity (R, t, s) with dst ~ s R src + t (Umeyama 1991) from (N, 3) matched
    points, by evo's formulas, so ATE agrees with ``evo_ape -a``. Degenerate inputs still give a
    minimiser (collinear points leave the roll about the line free; one distinct point gives R = I).
    Scale is 1 unless ``with_scale``.
    """
    src = np.asarray(src_xyz, dtype=float)
    dst = np.asarray(dst_xyz, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) == 0:
        raise SnapsGraphError(f"umeyama_alignment: need two matching (N, 3) arrays, got {src.shape} and {dst.shape}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise SnapsGraphError("umeyama_alignment: non-finite points")
    n = len(src)
    mean_src = src.mean(axis=0)
    mean_dst = dst.mean(axis=0)
    xs = src - mean_src
    ys = dst - mean_dst
    var_src = float((xs**2).sum()) / n  # eq. 36
    cov = ys.T @ xs / n  # eq. 38
    u, d, vt = np.linalg.svd(cov)
    s_mat = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        s_mat[2, 2] = -1.0  # eq. 43
    R = u @ s_mat @ vt  # eq. 40
    scale = float(np.trace(np.diag(d) @ s_mat) / var_src) if (with_scale and var_src > 0.0) else 1.0  # eq. 42
    t = mean_dst - scale * R @ mean_src  # eq. 41
    return R, t, scale
