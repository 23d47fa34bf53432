"""Paper 002: spiral vs Kalman-filter stochastic fiducial search, planning convergence."""
