"""Simulation: the truth trajectory and the IMU it drives. Imports estimation."""
