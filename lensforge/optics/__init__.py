"""lensforge.optics."""
