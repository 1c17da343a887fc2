"""Strapdown inertial mechanisation in a local ENU frame, and its error-state model.

Conventions (REP 103)
---------------------
* Navigation frame: local East-North-Up (ENU), metres; gravity is ``[0, 0, -g]``.
* Body frame: x forward, y left, z up (FLU). Positive pitch therefore puts the nose *down*.
* Quaternions are ``[x, y, z, w]`` (scalar last, as ``geometry_msgs/Quaternion`` and
  ``scipy.spatial.transform.Rotation``), and rotate body vectors into ENU (body -> ENU).
* Attitude error is the small rotation ``dtheta`` about the **ENU** axes with
  ``q_true = Exp(dtheta) * q_est`` (the convention of ROS ``PoseWithCovariance``, whose
  rotational covariance is about the fixed axes).
* Earth rate and transport rate are neglected (flat, non-rotating local frame): acceptable for
  a MEMS IMU over a mission area of tens of kilometres.

Discrete mechanisation (one IMU sample ``(omega, f)`` held over ``dt``)::

    q_half = Exp(omega * dt / 2)                 # body-frame half increment
    q_mid  = q * q_half,   q_new = q_mid * q_half
    v_new  = v + (C(q_mid) f + g) dt             # specific force rotated at mid-interval
    p_new  = p + (v + v_new) dt / 2

:func:`inverse_mechanisation` is its exact inverse, so a simulator can produce IMU samples
that reproduce a truth trajectory to machine precision (no integration-scheme error in tests).

The functions here are vectorised over leading axes except :class:`StrapdownStep`, which is
the allocation-light scalar step used at IMU rate by the filter.
"""

from __future__ import annotations

import math

import numpy as np

GRAVITY = 9.80665
"""Standard gravity (m/s^2), acting along -z of ENU."""

# Error-state layout shared by the EKF: [dp, dv, dtheta, dbg, dba], 3 components each.
IDX_P = slice(0, 3)
IDX_V = slice(3, 6)
IDX_TH = slice(6, 9)
IDX_BG = slice(9, 12)
IDX_BA = slice(12, 15)
DIM_ERR = 15


# --------------------------------------------------------------------------------------
# Vectorised quaternion / rotation helpers ([x, y, z, w], body -> ENU)
# --------------------------------------------------------------------------------------

def skew(v):
    """Cross-product matrix ``[v]x`` of ``v`` with shape (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def quat_multiply(a, b):
    """Hamilton product ``a * b`` of quaternions ``[x, y, z, w]``, shapes broadcast (..., 4)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ], axis=-1)


def quat_conjugate(q):
    """Inverse of unit quaternions ``[x, y, z, w]`` (..., 4)."""
    q = np.array(q, dtype=float)
    q[..., :3] *= -1.0
    return q


def quat_normalize(q):
    """Unit quaternion with non-negative scalar part (one representative per rotation)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def quat_exp(rotvec):
    """Quaternion of the rotation vector ``rotvec`` (rad), shape (..., 3) -> (..., 4)."""
    r = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a with its Taylor series near zero (avoids 0/0).
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([k * r, np.cos(half)], axis=-1)


def quat_log(q):
    """Rotation vector (rad) of unit quaternions ``[x, y, z, w]`` (..., 4) -> (..., 3).

    The shorter rotation is returned (angle in [0, pi]).
    """
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    vec = q[..., :3]
    s = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    small = s < 1e-9
    k = np.where(small, 2.0 / np.maximum(q[..., 3:4], 1e-300), angle / np.where(small, 1.0, s))
    return k * vec


def quat_to_matrix(q):
    """Rotation matrices (..., 3, 3) of unit quaternions ``[x, y, z, w]`` (..., 4)."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = np.moveaxis(q, -1, 0)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    m = np.stack([
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ], axis=-1)
    return m.reshape(q.shape[:-1] + (3, 3))


def quat_rotate(q, v):
    """Rotate body vectors ``v`` (..., 3) into ENU with quaternions ``q`` (..., 4)."""
    return np.einsum("...ij,...j->...i", quat_to_matrix(q), np.asarray(v, dtype=float))


def quat_from_euler(roll, pitch, yaw):
    """Body -> ENU quaternion from REP 103 Euler angles ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    With FLU body axes, yaw is measured counter-clockwise from East, and positive pitch is
    nose down. Arguments broadcast; the result has shape (..., 4).
    """
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(a, dtype=float)
                                             for a in (roll, pitch, yaw)))
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.stack([
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ], axis=-1)


def quat_to_euler(q):
    """(roll, pitch, yaw) in rad of body -> ENU quaternions, inverse of :func:`quat_from_euler`."""
    m = quat_to_matrix(q)
    roll = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    pitch = -np.arcsin(np.clip(m[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return roll, pitch, yaw


def attitude_error(q_true, q_est):
    """ENU-frame rotation vector ``dtheta`` with ``q_true = Exp(dtheta) * q_est`` (..., 3)."""
    return quat_log(quat_multiply(q_true, quat_conjugate(q_est)))


# --------------------------------------------------------------------------------------
# Mechanisation
# --------------------------------------------------------------------------------------

def _gravity_vector(gravity: float) -> np.ndarray:
    return np.array([0.0, 0.0, -gravity])


def mechanise(p, v, q, gyro, accel, dt, gravity: float = GRAVITY):
    """Vectorised discrete mechanisation (see module docstring) of one step per row.

    Parameters
    ----------
    p, v : array_like, (..., 3)
        Position (m) and velocity (m/s) in ENU at the start of the interval.
    q : array_like, (..., 4)
        Attitude body -> ENU at the start of the interval.
    gyro, accel : array_like, (..., 3)
        Bias-corrected angular rate (rad/s) and specific force (m/s^2), body frame.
    dt : float or array_like
        Interval length (s).
    gravity : float
        Magnitude of gravity (m/s^2).

    Returns
    -------
    p_new, v_new, q_new : ndarray
        State at the end of the interval.
    """
    dt = np.asarray(dt, dtype=float)[..., None] if np.ndim(dt) else float(dt)
    q_half = quat_exp(np.asarray(gyro, dtype=float) * (0.5 * dt))
    q_mid = quat_multiply(q, q_half)
    q_new = quat_normalize(quat_multiply(q_mid, q_half))
    v = np.asarray(v, dtype=float)
    v_new = v + (quat_rotate(q_mid, accel) + _gravity_vector(gravity)) * dt
    p_new = np.asarray(p, dtype=float) + 0.5 * (v + v_new) * dt
    return p_new, v_new, q_new


def inverse_mechanisation(t, velocity, quaternion, gravity: float = GRAVITY):
    """IMU samples that make :func:`mechanise` reproduce a sampled trajectory exactly.

    Sample ``k`` (``k >= 1``) is the angular rate and specific force held over
    ``(t[k-1], t[k]]``; row 0 is a copy of row 1 (there is no interval before the first
    epoch). Positions must be the trapezoidal integral of ``velocity`` for the reproduction
    to be exact (see :mod:`terrain_nav_ros.core.sim.trajectory_sim`).

    Parameters
    ----------
    t : array_like, (N,)
        Strictly increasing sample times (s).
    velocity : array_like, (N, 3)
        ENU velocity (m/s).
    quaternion : array_like, (N, 4)
        Body -> ENU attitude.
    gravity : float
        Magnitude of gravity (m/s^2).

    Returns
    -------
    gyro, accel : ndarray, (N, 3)
        Body angular rate (rad/s) and specific force (m/s^2).
    """
    t = np.asarray(t, dtype=float)
    q = np.asarray(quaternion, dtype=float)
    dt = np.diff(t)[:, None]
    dq = quat_multiply(quat_conjugate(q[:-1]), q[1:])  # body-frame increment
    gyro = quat_log(dq) / dt
    q_mid = quat_multiply(q[:-1], quat_exp(0.5 * gyro * dt))
    accel_enu = np.diff(np.asarray(velocity, dtype=float), axis=0) / dt - _gravity_vector(gravity)
    accel = np.einsum("nji,nj->ni", quat_to_matrix(q_mid), accel_enu)  # C^T a
    return np.vstack([gyro[:1], gyro]), np.vstack([accel[:1], accel])


# --------------------------------------------------------------------------------------
# Scalar fast path used by the filter at IMU rate
# --------------------------------------------------------------------------------------

class StrapdownStep:
    """Allocation-light single-sample mechanisation plus the error-state transition.

    Holds preallocated work arrays; :meth:`step` mutates the arrays it is given. The maths is
    the one of :func:`mechanise` written on Python floats, which is several times faster than
    numpy for 3- and 4-vectors.

    Parameters
    ----------
    gravity : float
        Magnitude of gravity (m/s^2).
    dim : int
        Size of the state (and of :attr:`F`): the 15 error states of the mechanisation, then
        any a filter adds that the IMU does not move (the EKF's wind).
    """

    def __init__(self, gravity: float = GRAVITY, dim: int = DIM_ERR):
        self.gravity = float(gravity)
        self.F = np.eye(dim)
        self._F_flat = self.F.reshape(-1)
        self._out = np.zeros(54)
        # Flat indices of the sample-dependent 3x3 blocks of F (top-left corners), in the
        # order v-theta, p-theta, v-ba, p-ba, theta-bg, v-bg.
        corners = ((3, 6), (0, 6), (3, 12), (0, 12), (6, 9), (3, 9))
        r3 = np.arange(3)
        self._flat = np.concatenate(
            [((r + r3[:, None]) * dim + c + r3).ravel() for r, c in corners])
        self.rate_enu = (0.0, 0.0, 0.0)          # of the last step, bias removed (rad/s)
        self.force_less_turn = (0.0, 0.0, 0.0)   # its ENU specific force less the turn

    def step(self, x, q, gyro, accel, dt):
        """Propagate nominal state in place and fill the error transition :attr:`F`.

        Parameters
        ----------
        x : ndarray, (dim,)
            ``[p, v, dtheta, bg, ba, ...]``; p and v are updated in place (dtheta must be
            zero). States past the fifteenth (a filter's own, constant here) are left alone.
        q : ndarray, (4,)
            Attitude ``[x, y, z, w]``, updated in place.
        gyro, accel : sequence of 3 floats
            Raw IMU sample (rad/s, m/s^2); the biases in ``x`` are removed here.
        dt : float
            Interval (s), > 0.

        Returns
        -------
        F : ndarray, (dim, dim)
            First-order discrete error-state transition over ``dt`` (a view of :attr:`F`,
            overwritten by the next call); the identity on the states past the fifteenth.
        """
        # Python floats: element access on numpy arrays costs more than the arithmetic.
        px, py, pz, v0x, v0y, v0z, _, _, _, bgx, bgy, bgz, bax, bay, baz = x[:DIM_ERR].tolist()
        gx, gy, gz = (float(g) for g in gyro)
        ax_, ay_, az_ = (float(a) for a in accel)
        wx, wy, wz = gx - bgx, gy - bgy, gz - bgz
        fx, fy, fz = ax_ - bax, ay_ - bay, az_ - baz
        # Half increment Exp(omega dt / 2) as a quaternion.
        hx, hy, hz = 0.5 * dt * wx, 0.5 * dt * wy, 0.5 * dt * wz
        a2 = hx * hx + hy * hy + hz * hz
        if a2 < 1e-12:
            k, cw = 0.5 - a2 / 48.0, 1.0 - a2 / 8.0
        else:
            a = math.sqrt(a2)
            k, cw = math.sin(0.5 * a) / a, math.cos(0.5 * a)
        dx, dy, dz, dw = k * hx, k * hy, k * hz, cw
        qx, qy, qz, qw = q.tolist()
        # q_mid = q * dq
        mx = qw * dx + qx * dw + qy * dz - qz * dy
        my = qw * dy - qx * dz + qy * dw + qz * dx
        mz = qw * dz + qx * dy - qy * dx + qz * dw
        mw = qw * dw - qx * dx - qy * dy - qz * dz
        # q_new = q_mid * dq, renormalised (drift control)
        nx = mw * dx + mx * dw + my * dz - mz * dy
        ny = mw * dy - mx * dz + my * dw + mz * dx
        nz = mw * dz + mx * dy - my * dx + mz * dw
        nw = mw * dw - mx * dx - my * dy - mz * dz
        inv = 1.0 / math.sqrt(nx * nx + ny * ny + nz * nz + nw * nw)
        q[:] = (nx * inv, ny * inv, nz * inv, nw * inv)
        # C(q_mid)
        xx, yy, zz = mx * mx, my * my, mz * mz
        xy, xz, yz = mx * my, mx * mz, my * mz
        wxq, wyq, wzq = mw * mx, mw * my, mw * mz
        c00, c01, c02 = 1 - 2 * (yy + zz), 2 * (xy - wzq), 2 * (xz + wyq)
        c10, c11, c12 = 2 * (xy + wzq), 1 - 2 * (xx + zz), 2 * (yz - wxq)
        c20, c21, c22 = 2 * (xz - wyq), 2 * (yz + wxq), 1 - 2 * (xx + yy)
        ax = c00 * fx + c01 * fy + c02 * fz
        ay = c10 * fx + c11 * fy + c12 * fz
        az = c20 * fx + c21 * fy + c22 * fz
        # velocity and position (trapezoid)
        v1x, v1y, v1z = v0x + ax * dt, v0y + ay * dt, v0z + (az - self.gravity) * dt
        # What the filter's levelling sums: the ENU specific force, less the turn (the ENU
        # body rate x the velocity).
        rx = c00 * wx + c01 * wy + c02 * wz
        ry = c10 * wx + c11 * wy + c12 * wz
        rz = c20 * wx + c21 * wy + c22 * wz
        self.rate_enu = (rx, ry, rz)
        self.force_less_turn = (ax - (ry * v1z - rz * v1y), ay - (rz * v1x - rx * v1z),
                                az - (rx * v1y - ry * v1x))
        x[0:6] = (px + 0.5 * (v0x + v1x) * dt, py + 0.5 * (v0y + v1y) * dt,
                  pz + 0.5 * (v0z + v1z) * dt, v1x, v1y, v1z)
        return self._fill_transition(dt, (c00, c01, c02, c10, c11, c12, c20, c21, c22),
                                     ax, ay, az)

    def _fill_transition(self, dt, c, ax, ay, az):
        """Closed-form F = I + A dt + (A dt)^2/2 restricted to its non-zero blocks.

        ``A`` is the continuous error dynamics with ENU attitude error:
        ``dp' = dv``, ``dv' = -[C f]x dtheta - C dba``, ``dtheta' = -C dbg``, biases constant.
        The second-order terms kept are the ones that couple position to attitude and to the
        accelerometer bias, and velocity to the gyro bias (they matter once dt grows, e.g.
        when replaying after an IMU gap).
        """
        h = 0.5 * dt * dt
        c00, c01, c02, c10, c11, c12, c20, c21, c22 = c
        # [C f]x, the skew of the ENU specific force, and [C f]x C (row-major, 3x3 each).
        sk = (0.0, -az, ay, az, 0.0, -ax, -ay, ax, 0.0)
        skc = (-az * c10 + ay * c20, -az * c11 + ay * c21, -az * c12 + ay * c22,
               az * c00 - ax * c20, az * c01 - ax * c21, az * c02 - ax * c22,
               -ay * c00 + ax * c10, -ay * c01 + ax * c11, -ay * c02 + ax * c12)
        md, mh = -dt, -h
        # Blocks in the order of self._flat: v-theta, p-theta, v-ba, p-ba, theta-bg, v-bg.
        self._out[:] = ([e * md for e in sk] + [e * mh for e in sk]
                        + [e * md for e in c] + [e * mh for e in c]
                        + [e * md for e in c] + [e * h for e in skc])
        F = self.F
        self._F_flat[self._flat] = self._out  # view of F; faster than F.flat
        F[0, 3] = F[1, 4] = F[2, 5] = dt
        return F


def process_noise(dt: float, gyro_noise: float, accel_noise: float,
                  gyro_bias_rw: float, accel_bias_rw: float, out=None) -> np.ndarray:
    """Closed-form discrete process noise over ``dt`` for the 15-state error model.

    Accelerometer white noise (density ``accel_noise``, m/s^2/sqrt(Hz)) enters velocity and,
    integrated, position (the classic ``dt^3/3, dt^2/2, dt`` block); gyro white noise
    (rad/s/sqrt(Hz)) enters attitude; bias random walks (rad/s^2/sqrt(Hz), m/s^3/sqrt(Hz))
    enter the biases. All blocks are isotropic, so the rotation of the noise into ENU drops
    out. Cross terms of second order in dt through the bias walks are neglected.

    Returns
    -------
    Q : ndarray, (15, 15)
    """
    Q = np.zeros((DIM_ERR, DIM_ERR)) if out is None else out
    Q.fill(0.0)
    qa, qg = accel_noise**2, gyro_noise**2
    i3 = np.arange(3)
    Q[i3, i3] = qa * dt**3 / 3.0
    Q[i3, i3 + 3] = Q[i3 + 3, i3] = qa * dt**2 / 2.0
    Q[i3 + 3, i3 + 3] = qa * dt
    Q[i3 + 6, i3 + 6] = qg * dt
    Q[i3 + 9, i3 + 9] = gyro_bias_rw**2 * dt
    Q[i3 + 12, i3 + 12] = accel_bias_rw**2 * dt
    return Q
