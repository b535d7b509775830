"""Heading fuser: quaternion EKF AHRS with adaptive magnetometer noise and a gyro fallback."""
