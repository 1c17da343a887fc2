"""Estimation: the strapdown mechanisation, the error-state EKF and its parameters, IMU
stamp screening, the barometer model and the autopilots' frame conventions; and what the
``ekf`` node decides about its inputs and reports (:mod:`.ekf_inputs`, :mod:`.ekf_health`).
Imports no other stage but terrain's geodesy."""
