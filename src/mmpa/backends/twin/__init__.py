"""The MuJoCo digital twin: the TRUE world and robot, sensors with the error model (profiles
ideal, reference, realistic, harsh), and ground-truth accessors for evaluation only.
Algorithm code never imports this package."""
