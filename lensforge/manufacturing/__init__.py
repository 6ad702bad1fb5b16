"""lensforge.manufacturing."""
