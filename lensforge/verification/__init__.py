"""lensforge.verification."""
