"""lensforge.calibration: what a user runs on real data (pose estimation, hand-eye AX = ZB,
robot kinematics and noise, calibration-pose design, joint as-built calibration through the
lens and its pose design)."""
