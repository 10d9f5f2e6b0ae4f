"""Simulation rigs, one per level: the service on the simulated rack (rig), the whole system (system), calibration (calibration), the demo commander (demo)."""
