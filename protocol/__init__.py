"""Wire contracts shared by every fleetmpc process: the scenario file, Zenoh keys and messages,
and the MAVLink field mapping."""
