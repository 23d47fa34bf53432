"""Calibration: ChArUco board detection and pose, eye-in-hand (hand-eye) calibration."""
