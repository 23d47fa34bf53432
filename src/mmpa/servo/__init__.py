"""Visual servoing and the tracking grasp (paper 001 §3.2.2, eq. 9-14).

- :mod:`.ibvs`: point-feature interaction matrix with depth, camera velocity, arm Jacobian
  pseudo-inverse (eq. 9-12), gain and velocity limits;
- :mod:`.nullspace`: manipulability (eq. 14) gradient projected into the task null space
  (eq. 13);
- :mod:`.predictor`: a constant-velocity Kalman filter on the object's 3D position;
- :mod:`.grasp`: the tracking grasp over the robot interfaces, composing :mod:`.tracker`
  (detection -> target estimate), :mod:`.search` (second views), :mod:`.stream` (the
  streamed set-points and their limits) and :mod:`.descent` (descent onto the object);
  settings :mod:`.config`, poses :mod:`.pose`. Measurements: ``docs/servo.md``.

Capability code: numpy arrays and the robot interfaces only, never the simulator.
"""
