"""Simulated and real I2S data: IMU simulation, mocap kinematics cache, splits, windows."""
