"""lensforge.verification: simulation of the calibration (as-built study, runner, budget,
scenario, estimation study, their plots)."""
