"""The simulated vehicle: truth plant, scripted target, and the MAVLink autopilot around them."""
