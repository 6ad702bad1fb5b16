"""lensforge.calibration: what a user runs on real data (pose estimation, hand-eye AX = ZB,
robot kinematics and noise, calibration-pose design)."""
