"""lensforge: design, print and verify freeform lenses for Shack-Hartmann pose
estimation and robot-world-hand-eye calibration.

Public API (``import lensforge as lf``; documented in docs/api.md, generated from the
docstrings by docs/make_api.py); names resolve lazily so that importing the package stays
cheap and ``optics`` never pulls in the heavier modules. ``_EXPORTS`` is the one list of
names (``__all__`` is built from it); type checkers see the same names through the
``TYPE_CHECKING`` imports below (the package ships ``py.typed``), which
tests/test_public_api.py keeps identical to ``_EXPORTS``.

Units: lengths mm, angles rad, Zernike coefficients um of wavefront in Noll order
(RMS-normalised); the conversions ``noll_to_osa`` / ``noll_to_thorlabs`` / ``to_osa_vector``
... exist for input and output only. Pose vectors are (tx, ty, tz, rx, ry, rz) in mm and
a rotation vector in rad; ``pose_to_matrix`` / ``matrix_to_pose`` convert to 4x4 transforms.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    # optics
    "Bench": "lensforge.optics.bench",
    "load_bench": "lensforge.optics.bench",
    "save_bench": "lensforge.optics.bench",
    "Lens": "lensforge.optics.lens",
    "resolve_lens": "lensforge.optics.lens",
    "LensSpec": "lensforge.optics.lens",
    "paper_lens": "lensforge.optics.lens",
    "PAPER_LENSES": "lensforge.optics.lens",
    "load_lens": "lensforge.optics.lens",
    "lens_conventions": "lensforge.optics.lens",
    "Conic": "lensforge.optics.surfaces",
    "Polynomial": "lensforge.optics.surfaces",
    "ExtendedPolynomial": "lensforge.optics.surfaces",
    "ZernikeSag": "lensforge.optics.surfaces",
    "Freeform": "lensforge.optics.surfaces",
    "load_material": "lensforge.optics.materials",
    "measure": "lensforge.optics.shack_hartmann",
    "ForwardModel": "lensforge.optics.shack_hartmann",
    "sensitivity": "lensforge.optics.sensitivity",
    "metrics": "lensforge.optics.sensitivity",
    "Metrics": "lensforge.optics.sensitivity",
    "jacobian": "lensforge.optics.sensitivity",
    "observability": "lensforge.optics.sensitivity",
    "trace_rays": "lensforge.optics.trace",
    # Zernike index and vector conversions (Noll inside; OSA/ANSI and Thorlabs at the edges)
    "noll_to_nm": "lensforge.optics.zernike",
    "nm_to_noll": "lensforge.optics.zernike",
    "noll_to_osa": "lensforge.optics.zernike",
    "osa_to_noll": "lensforge.optics.zernike",
    "noll_to_thorlabs": "lensforge.optics.zernike",
    "thorlabs_to_noll": "lensforge.optics.zernike",
    "to_osa_vector": "lensforge.optics.zernike",
    "from_osa_vector": "lensforge.optics.zernike",
    "to_thorlabs_vector": "lensforge.optics.zernike",
    "from_thorlabs_vector": "lensforge.optics.zernike",
    # poses (SE(3) helpers)
    "DOF_NAMES": "lensforge.optics.pose",
    "pose_to_matrix": "lensforge.optics.pose",
    "matrix_to_pose": "lensforge.optics.pose",
    "invert_poses": "lensforge.optics.pose",
    "transform_error": "lensforge.optics.pose",
    # design
    "optimize_design": "lensforge.design.optimize",
    "Design": "lensforge.design.design_file",
    "load_design": "lensforge.design.design_file",
    "save_design": "lensforge.design.design_file",
    # manufacturing and interchange
    "export_stl": "lensforge.manufacturing.mesh",
    "export_step": "lensforge.manufacturing.step",
    "export_lens": "lensforge.manufacturing.report",
    "ExportReport": "lensforge.manufacturing.report",
    "FeatureSpec": "lensforge.manufacturing.features",
    "write_optiland": "lensforge.manufacturing.prescription",
    "optiland_model": "lensforge.manufacturing.prescription",
    "opticstudio_prescription": "lensforge.manufacturing.prescription",
    "write_prescription": "lensforge.manufacturing.prescription",
    "sample_as_built": "lensforge.asbuilt.tolerances",
    "Tolerances": "lensforge.asbuilt.tolerances",
    "load_tolerances": "lensforge.asbuilt.tolerances",
    # calibration
    "estimate_pose": "lensforge.calibration.pose_estimation",
    "estimate_poses_batch": "lensforge.calibration.pose_estimation",
    "solve_handeye": "lensforge.calibration.handeye",
    "HandEyeResult": "lensforge.calibration.handeye",
    "plan": "lensforge.calibration.session",
    "calibrate": "lensforge.calibration.session",
    "estimate": "lensforge.calibration.session",
    "load_robot": "lensforge.calibration.robot",
    "read_robot_poses": "lensforge.calibration.formats",
    "read_wfs": "lensforge.calibration.formats",
    # verification (simulation of the calibration)
    "verify": "lensforge.verification.study",
    "simulate_session": "lensforge.verification.session_sim",
    "tolerance_budget": "lensforge.verification.budget",
    "sensitivity_analysis": "lensforge.verification.budget",
    # plots
    "design_plots": "lensforge.plots.design",
    # errors
    "LensforgeError": "lensforge.errors",
    "ConfigError": "lensforge.errors",
}

__all__ = sorted(_EXPORTS) + ["__version__"]

if TYPE_CHECKING:  # the same names, eagerly, for type checkers and IDEs
    from .calibration.formats import read_robot_poses, read_wfs
    from .calibration.handeye import HandEyeResult, solve_handeye
    from .calibration.pose_estimation import estimate_pose, estimate_poses_batch
    from .calibration.robot import load_robot
    from .calibration.session import calibrate, estimate, plan
    from .design.design_file import Design, load_design, save_design
    from .design.optimize import optimize_design
    from .errors import ConfigError, LensforgeError
    from .manufacturing.features import FeatureSpec
    from .manufacturing.mesh import export_stl
    from .manufacturing.prescription import (opticstudio_prescription, optiland_model, write_optiland,
                                             write_prescription)
    from .manufacturing.report import ExportReport, export_lens
    from .manufacturing.step import export_step
    from .asbuilt.tolerances import Tolerances, load_tolerances, sample_as_built
    from .optics.bench import Bench, load_bench, save_bench
    from .optics.lens import PAPER_LENSES, Lens, LensSpec, lens_conventions, load_lens, paper_lens, resolve_lens
    from .optics.materials import load_material
    from .optics.pose import DOF_NAMES, invert_poses, matrix_to_pose, pose_to_matrix, transform_error
    from .optics.sensitivity import Metrics, jacobian, metrics, observability, sensitivity
    from .optics.shack_hartmann import ForwardModel, measure
    from .optics.surfaces import Conic, ExtendedPolynomial, Freeform, Polynomial, ZernikeSag
    from .optics.trace import trace_rays
    from .optics.zernike import (from_osa_vector, from_thorlabs_vector, nm_to_noll, noll_to_nm, noll_to_osa,
                                 noll_to_thorlabs, osa_to_noll, thorlabs_to_noll, to_osa_vector,
                                 to_thorlabs_vector)
    from .plots.design import design_plots
    from .verification.budget import sensitivity_analysis, tolerance_budget
    from .verification.session_sim import simulate_session
    from .verification.study import verify


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lensforge' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
