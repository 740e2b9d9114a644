"""The launcher: a fleet's processes on this machine (`fleetmpc up`) or as a docker compose
file (`fleetmpc compose`), from one process list."""
