"""lensforge: design, print and verify freeform lenses for Shack-Hartmann pose
estimation and robot-world-hand-eye calibration.

Public API (``import lensforge as lf``); names resolve lazily so that importing the
package stays cheap and ``optics`` never pulls in the heavier modules.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    # optics
    "Bench": "lensforge.optics.bench",
    "load_bench": "lensforge.optics.bench",
    "save_bench": "lensforge.optics.bench",
    "Lens": "lensforge.optics.lens",
    "resolve_lens": "lensforge.optics.lens",
    "paper_lens": "lensforge.optics.lens",
    "PAPER_LENSES": "lensforge.optics.lens",
    "load_material": "lensforge.optics.materials",
    "measure": "lensforge.optics.shack_hartmann",
    "ForwardModel": "lensforge.optics.shack_hartmann",
    "sensitivity": "lensforge.optics.sensitivity",
    "metrics": "lensforge.optics.sensitivity",
    "Metrics": "lensforge.optics.sensitivity",
    "jacobian": "lensforge.optics.sensitivity",
    "observability": "lensforge.optics.sensitivity",
    "trace_rays": "lensforge.optics.trace",
    # design
    "optimize_design": "lensforge.design.optimize",
    "Design": "lensforge.design.design_file",
    "load_design": "lensforge.design.design_file",
    "save_design": "lensforge.design.design_file",
    # manufacturing
    "export_stl": "lensforge.manufacturing.mesh",
    "export_step": "lensforge.manufacturing.step",
    "sample_as_built": "lensforge.manufacturing.tolerances",
    "Tolerances": "lensforge.manufacturing.tolerances",
    "load_tolerances": "lensforge.manufacturing.tolerances",
    # calibration
    "estimate_pose": "lensforge.calibration.pose_estimation",
    "estimate_poses_batch": "lensforge.calibration.pose_estimation",
    "solve_handeye": "lensforge.calibration.handeye",
    "plan": "lensforge.calibration.session",
    "calibrate": "lensforge.calibration.session",
    "estimate": "lensforge.calibration.session",
    "load_robot": "lensforge.calibration.robot",
    "read_robot_poses": "lensforge.calibration.formats",
    "read_wfs": "lensforge.calibration.formats",
    # verification (simulation of the calibration)
    "verify": "lensforge.verification.study",
    "simulate_session": "lensforge.verification.session_sim",
    # errors
    "LensforgeError": "lensforge.errors",
    "ConfigError": "lensforge.errors",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lensforge' has no attribute {name!r}")


def __dir__():
    return __all__
