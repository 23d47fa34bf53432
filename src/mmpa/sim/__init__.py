"""The MuJoCo digital twin: the TRUE world and robot, sensors with the reference error model,
and ground-truth accessors for evaluation only. Algorithm code never imports this package."""
