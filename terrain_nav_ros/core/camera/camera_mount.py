"""Where the camera sits on the aircraft: body (REP 103 FLU) -> camera optical frame.

The default is the down-looking survey camera: optical axis along body -z, image top towards
the nose, image right towards the right wing. Both the flight simulator and camera_ingest use
:func:`camera_rotation` so a simulated frame is projected back with the same geometry.
"""

from __future__ import annotations

import numpy as np

from ..estimation.strapdown import quat_from_euler, quat_to_matrix

# Columns: optical x (image right) = body -y, optical y (image down) = body -x (tail),
# optical z (viewing direction) = body -z (down).
R_BODY_OPTICAL_NADIR = np.array([[0.0, -1.0, 0.0],
                                 [-1.0, 0.0, 0.0],
                                 [0.0, 0.0, -1.0]])


def mount_rotation(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Body -> optical rotation of a nadir camera tilted by small mount angles (rad, FLU)."""
    tilt = quat_to_matrix(quat_from_euler(roll, pitch, yaw))
    return tilt @ R_BODY_OPTICAL_NADIR


def camera_rotation(q_enu_body, r_body_optical=R_BODY_OPTICAL_NADIR) -> np.ndarray:
    """Optical -> ENU rotation from the body attitude quaternion ``[x, y, z, w]``."""
    return quat_to_matrix(np.asarray(q_enu_body, float)) @ r_body_optical


def chained_rotation(transforms: dict, base: str, frame: str) -> np.ndarray | None:
    """Rotation ``base`` -> ``frame`` through static transforms, or None when ``frame`` does
    not hang under ``base`` (a frame missing, or a loop).

    ``transforms`` maps each child frame to ``(parent, R_parent_child)``, as a tree of
    ``/tf_static`` holds them (``base_link -> camera_link -> camera_optical``); the columns
    of the result are ``frame``'s axes in ``base``, as :func:`mount_rotation`'s are.
    """
    rotation, seen = np.eye(3), set()
    while frame != base:
        if frame in seen or frame not in transforms:
            return None
        seen.add(frame)
        parent, r_parent_child = transforms[frame]
        rotation = r_parent_child @ rotation
        frame = parent
    return rotation


def mount_angles(r_body_optical: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad, FLU) of a mount, the inverse of :func:`mount_rotation`."""
    from scipy.spatial.transform import Rotation

    tilt = np.asarray(r_body_optical, float) @ R_BODY_OPTICAL_NADIR.T
    return tuple(float(a) for a in Rotation.from_matrix(tilt).as_euler("xyz"))
