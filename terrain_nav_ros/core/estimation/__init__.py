"""Estimation: the strapdown mechanisation, the error-state EKF and its parameters, IMU
stamp screening, the barometer model and the autopilots' frame conventions. Imports no other
stage."""
