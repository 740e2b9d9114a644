"""The ground station: telemetry, plans and metrics into Rerun, the feasibility check, the
recording's reader, and the reports and figures made from a record."""
