"""Calibration through the lens: joint as-built calibration (more modules move here with the consolidation)."""
