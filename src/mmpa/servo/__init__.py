"""Visual servoing and the tracking grasp (paper 001 §3.2.2, eq. 9-14).

- :mod:`.ibvs`: point-feature interaction matrix with depth, camera velocity, arm Jacobian
  pseudo-inverse (eq. 9-12), gain and velocity limits;
- :mod:`.nullspace`: manipulability (eq. 14) gradient projected into the task null space
  (eq. 13);
- :mod:`.predictor`: a constant-velocity Kalman filter on the object's 3D position;
- :mod:`.grasp`: approach, close, lift; the tracking grasp loop over the robot interfaces.

Capability code: numpy arrays and the robot interfaces only, never the simulator.
"""
