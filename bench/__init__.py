"""Benchmarks (`fleetmpc bench`): the agent's step against a cvxpy rebuild, the lockstep speed,
the ground station's logging cost, and a side-by-side run against another checkout."""
