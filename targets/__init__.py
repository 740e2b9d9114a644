"""Target sources: where the fleet's target observations come from, all in one place.

- `script`: the scripted target (`fleetmpc.targets.script`), a pure function of time (default);
- `mavlink`: another MAVLink system's GLOBAL_POSITION_INT or FOLLOW_TARGET
  (`fleetmpc.targets.mavlink_source`), a second autopilot or a ground station's follow-me stream;
- `track`: a recorded track (`fleetmpc.targets.track`, read by `fleetmpc.targets.track_file`
  from a CSV or a MAVLink telemetry log), replayed live or flown in lockstep as a scenario target.

Every live source's fixes pass the same screen (`fleetmpc.targets.screen`: NaN, wrong system,
repeats, time going backwards or ahead, jumps), are placed in the fleet's local North-East frame
about the scenario's home (`fleetmpc.protocol.local_frame.ned_from_geodetic`) and stamped on
fleet time through the source's clock as estimated (`fleetmpc.targets.clock_map`), then published
as `TargetObservation`s by `fleetmpc target` (`fleetmpc.targets.process`).
"""
