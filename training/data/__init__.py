"""Readers of the shared data, IMU simulation and datasets."""
