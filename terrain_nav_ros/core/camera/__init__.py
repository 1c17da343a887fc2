"""Camera geometry: intrinsics and ground projection, orthorectification, the camera mount
and the pose buffer. Imports terrain and estimation (rotations)."""
