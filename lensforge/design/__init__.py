"""lensforge.design."""
