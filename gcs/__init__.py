"""Ground side: the fleet launcher, the ground station, the lockstep simulation and reports."""
