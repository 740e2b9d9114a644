"""The lockstep simulation: the whole fleet in one process, deterministic for a seed
(`fleetmpc sim`), and the scenario suite over seeds (`fleetmpc suite`)."""
