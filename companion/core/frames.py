"""Frames and rotations (docs/derivations/frames.md).

Conventions used everywhere in the package:

* world: local NED (x north, y east, z down), metres;
* body: FRD (x forward, y right, z down); attitude as roll, pitch, yaw (ZYX Euler, rad);
* camera: OpenCV (x right, y down, z along the optical axis).

``R_a_b`` maps vectors expressed in frame *b* into frame *a*; ``p_a`` is a position in frame *a*.
Quaternions are scalar-first ``(w, x, y, z)``, as MAVLink ATTITUDE_QUATERNION uses, and
``q_a_b`` corresponds to ``R_a_b``.  All functions broadcast over leading dimensions.
"""

from __future__ import annotations

import math

import numpy as np

from companion.errors import InputError

#: Body FRD -> camera (OpenCV) for a forward-looking camera: cam_x = body_y, cam_y = body_z, cam_z = body_x.
R_CAM_BODY_FORWARD = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains NaN or inf")
    return a


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` with ``[v]x @ w == v × w``; shape (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    K = np.zeros(v.shape[:-1] + (9,))
    K[..., _SKEW_POS] = v  # (2,1) = v0, (0,2) = v1, (1,0) = v2
    K[..., _SKEW_NEG] = -v  # (1,2) = −v0, (2,0) = −v1, (0,1) = −v2
    return K.reshape(v.shape[:-1] + (3, 3))


_SKEW_POS = np.array([7, 2, 3])  # flat indices in a row-major 3×3 matrix
_SKEW_NEG = np.array([5, 6, 1])
#: :func:`skew` as a linear map: ``[v]x == (v @ SKEW_MAP).reshape(3, 3)`` for finite v (one product per batch)
SKEW_MAP = np.zeros((3, 9))
SKEW_MAP[[0, 1, 2], _SKEW_POS] = 1.0
SKEW_MAP[[0, 1, 2], _SKEW_NEG] = -1.0


def is_orthonormal(R: np.ndarray) -> bool:
    """Rᵀ R = I to the tolerance of ``np.allclose(Rᵀ R, I, atol=1e-6)`` (its default rtol 1e-5), for one (3, 3) R."""
    return bool(np.all(np.abs(R.T @ R - _I3) <= _ORTHONORMAL_TOL))


_I3 = np.eye(3)
_ORTHONORMAL_TOL = 1e-6 + 1e-5 * _I3


def euler_zyx_to_R(roll, pitch, yaw) -> np.ndarray:
    """``R_world_body`` from ZYX Euler angles (yaw about z, then pitch about y, then roll about x).

    This is the attitude MAVLink ATTITUDE reports: body FRD relative to local NED.
    """
    roll, pitch, yaw = (np.asarray(a, dtype=float) for a in (roll, pitch, yaw))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    R = np.empty(np.broadcast_shapes(cr.shape, cp.shape, cy.shape) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def euler_zyx_to_R_scalar(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """:func:`euler_zyx_to_R` of one attitude (floats) with :mod:`math` instead of numpy ufuncs on
    0-d arrays (a few µs instead of tens, for per-frame use): the same expressions in the same
    order, hence the same matrix wherever numpy's cos and sin round as the C library's do (the
    tests compare the two bit for bit)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def R_to_euler_zyx(R_world_body: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_zyx_to_R`: returns (..., 3) = roll, pitch, yaw in rad."""
    R = np.asarray(R_world_body, dtype=float)
    pitch = -np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (normalized here)."""
    q = _finite("quaternion", q)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise InputError("quaternion has zero norm")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return R


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with w ≥ 0 of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    q = np.empty((R.shape[0], 4))
    tr = np.trace(R, axis1=1, axis2=2)
    diag = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], 1)
    case = np.argmax(np.concatenate([tr[:, None], diag], 1), axis=1)
    for c in range(4):  # four branches, each vectorized over the rows that take it
        m = case == c
        if not np.any(m):
            continue
        r = R[m]
        if c == 0:
            s = np.sqrt(1.0 + tr[m]) * 2
            q[m] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s], 1)
        elif c == 1:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[m] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s], 1)
        elif c == 2:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[m] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s], 1)
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[m] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(shape + (4,))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, s: float | np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions, ``s`` in [0, 1]."""
    q0 = np.asarray(q0, float)
    q1 = np.asarray(q1, float)
    s = np.asarray(s, float)[..., None]
    d = np.sum(q0 * q1, -1, keepdims=True)
    q1 = np.where(d < 0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    small = theta < 1e-8
    st = np.where(small, 1.0, np.sin(theta))
    w0 = np.where(small, 1 - s, np.sin((1 - s) * theta) / st)
    w1 = np.where(small, s, np.sin(s * theta) / st)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


# -- one attitude at a time ---------------------------------------------------------------------------
# The telemetry buffer converts every ATTITUDE and interpolates poses several times a frame; on
# 0-d and (4,) arrays the vectorized functions above cost tens of numpy calls each (~0.1–0.3 ms a
# call on a small computer).  These forms take Python floats: the same expressions in the same
# order (sums left to right, as numpy reduces fewer than eight elements), IEEE-exact arithmetic in
# Python, and numpy's own ufuncs for the transcendental functions (numpy may use its SIMD versions
# rather than the C library's), so they give the vectorized results bit for bit (the tests check it).

def R_to_quat_scalar(R) -> np.ndarray:
    """:func:`R_to_quat` of one (3, 3) rotation matrix (Shepperd's method), bit for bit."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = (map(float, row) for row in np.asarray(R, float))
    tr = 0.0 + r00 + r11 + r22
    vals = (tr, r00, r11, r22)
    case = vals.index(max(vals))  # the first of equal maxima, like np.argmax (no NaN: checked by the callers)
    if case == 0:
        s = float(np.sqrt(1.0 + tr)) * 2
        q = [0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s]
    elif case == 1:
        s = float(np.sqrt(1.0 + r00 - r11 - r22)) * 2
        q = [(r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s]
    elif case == 2:
        s = float(np.sqrt(1.0 + r11 - r00 - r22)) * 2
        q = [(r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s]
    else:
        s = float(np.sqrt(1.0 + r22 - r00 - r11)) * 2
        q = [(r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s]
    if q[0] < 0:
        q = [-c for c in q]
    return np.array(q)


def quat_to_R_scalar(q) -> np.ndarray:
    """:func:`quat_to_R` of one quaternion ``(w, x, y, z)`` (normalized here), bit for bit; the same
    :class:`~companion.errors.InputError` on NaN, inf or a zero norm."""
    w, x, y, z = (float(c) for c in np.asarray(q, float).reshape(4))
    if not (math.isfinite(w) and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise InputError("quaternion contains NaN or inf")
    n = float(np.sqrt(0.0 + w * w + x * x + y * y + z * z))
    if n < 1e-12:
        raise InputError("quaternion has zero norm")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def R_to_euler_zyx_scalar(R) -> np.ndarray:
    """:func:`R_to_euler_zyx` of one (3, 3) matrix: (3,) roll, pitch, yaw in rad, bit for bit."""
    R = np.asarray(R, float)
    pitch = -float(np.arcsin(min(max(float(R[2, 0]), -1.0), 1.0)))
    roll = float(np.arctan2(float(R[2, 1]), float(R[2, 2])))
    yaw = float(np.arctan2(float(R[1, 0]), float(R[0, 0])))
    return np.array([roll, pitch, yaw])


def quat_slerp_scalar(q0, q1, s: float) -> np.ndarray:
    """:func:`quat_slerp` of two quaternions (4,) at one ``s``, bit for bit."""
    a = [float(c) for c in q0]
    b = [float(c) for c in q1]
    s = float(s)
    d = 0.0 + a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
    if d < 0:
        b = [-c for c in b]
    d = abs(d)
    theta = float(np.arccos(min(max(d, -1.0), 1.0)))
    if theta < 1e-8:
        w0, w1 = 1 - s, s
    else:
        st = float(np.sin(theta))
        w0 = float(np.sin((1 - s) * theta)) / st
        w1 = float(np.sin(s * theta)) / st
    q = [w0 * a[i] + w1 * b[i] for i in range(4)]
    n = float(np.sqrt(0.0 + q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]))
    return np.array([c / n for c in q])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation matrix of the rotation vector ``phi`` (..., 3)."""
    phi = np.asarray(phi, float)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24, (1 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of ``R`` (angle < π), inverse of :func:`so3_exp`."""
    R = np.asarray(R, float)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    th = np.arccos(cos)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    small = th < 1e-6
    s = np.where(small, 1.0, np.sin(th))
    f = np.where(small, 0.5 + th**2 / 12, th / (2 * s))
    return f[..., None] * w


def se3_twist(R_world_cam0, p_world_cam0, R_world_cam1, p_world_cam1, dt: float):
    """Constant body-frame twist that carries camera pose 0 to pose 1 in ``dt`` (the inputs of docs/derivations/ekf_landmark.md).

    Returns ``(v_cam, w_cam)``: the camera's linear velocity and angular rate in its own frame,
    such that a point obeys dP/dt = −v − w × P (the seed-000 motion model) along the whole step.
    """
    if not dt > 0:
        raise InputError(f"dt must be > 0, got {dt}")
    R_rel = np.swapaxes(R_world_cam0, -1, -2) @ R_world_cam1  # R_cam0_cam1
    t_rel = np.einsum("...ji,...j->...i", R_world_cam0, np.asarray(p_world_cam1) - np.asarray(p_world_cam0))
    phi = so3_log(R_rel)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    # V^{-1} of the SE(3) exponential
    c = np.where(small, 1.0 / 12.0, (1 - ths * np.sin(ths) / (2 * (1 - np.cos(ths)))) / ths**2)
    V_inv = np.eye(3) - 0.5 * K + c * (K @ K)
    rho = np.einsum("...ij,...j->...i", V_inv, t_rel)
    return rho / dt, phi / dt


def mount_rotation(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """``R_cam_body`` of a camera mounted with the given extra rotation relative to forward-looking.

    The angles rotate the camera relative to the body (ZYX, degrees): yaw turns it right, pitch
    tilts it up, roll about its optical axis.  Zero angles give :data:`R_CAM_BODY_FORWARD`.
    """
    R_body_mount = euler_zyx_to_R(np.radians(roll_deg), np.radians(pitch_deg), np.radians(yaw_deg))
    return R_CAM_BODY_FORWARD @ R_body_mount.T
