"""lensforge.design: parameterisations, criteria, constraints, optimisers, design files."""

import os
from pathlib import Path

# pyswarms configures logging from $LOG_CFG; point it at a no-op config so that it does
# not add a root file handler writing report.log into the user's folder (a user's own
# LOG_CFG still wins).
os.environ.setdefault("LOG_CFG", str(Path(__file__).with_name("pyswarms_logging.yaml")))
