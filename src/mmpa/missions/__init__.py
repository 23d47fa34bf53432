"""Missions compose capabilities over the robot interfaces (never the simulator)."""
