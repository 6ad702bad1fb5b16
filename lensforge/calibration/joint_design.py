"""Calibration poses for the joint problem: (X, Z) and the as-built lens theta together.

The hand-eye pose design (``pose_design``) sees only the lens-pose covariance. With
the lens unknown, what a pose contributes depends on how the as-built deviations
theta show in its Zernikes beside the pose directions. Each candidate lens pose c
(pose vector relative to nominal, at the nominal grasp and sensor pose) contributes
the information of the joint problem (``joint``) with its own robot pose error
eliminated:

    I_c = Jg^T Jg - Jg^T Ja (Ja^T Ja + Sigma_A^-1)^-1 Ja^T Jg,   Jg = [S dX, S dZ, J_theta],

S and J_theta the whitened Jacobians of h in pose and theta at c. The design
maximises the Ds-criterion of Z, -log det Cov(Z) with Cov = (sum_c I_c + prior)^-1
(theta and X as nuisances; the prior on theta is the tolerance model's N(0, I)), by
greedy forward selection and exchange passes over the candidates (a pose may be
chosen more than once). Candidates must light the pupil for the mean as-built lens
(``ForwardModel.evaluate(...).valid``) and the chosen ones must be reachable
(inverse kinematics, ``robot.flange_pose``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..asbuilt.joint_information import pose_information, select_ds, theta_prior, z_sigma
from ..asbuilt.lens_params import LensParameterisation

__all__ = ["JointDesign", "candidate_information", "predicted_joint_uncertainty", "design_joint_poses",
           "box_candidates"]


def box_candidates(rng: np.random.Generator, span, n_random: int = 400) -> np.ndarray:
    """Candidate lens poses (m, 6): the 64 corners of the box +-span (mm, rad), its 12
    face centres and n_random uniform points inside."""
    span = np.asarray(span, dtype=float)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=6))) * span
    faces = np.concatenate([np.diag(span), -np.diag(span)])
    return np.concatenate([corners, faces, rng.uniform(-1.0, 1.0, (n_random, 6)) * span])


def candidate_information(bench, param: LensParameterisation, scene, x, robot_cov=None, measurement=None):
    """(I (m, G, G) information per candidate pose x (m, 6), lit (m,)); G = 12 + k.
    Unlit candidates get zero information."""
    from .joint import JointProblem

    x = np.atleast_2d(np.asarray(x, dtype=float))
    robot_cov = scene.noise.cov if robot_cov is None else np.asarray(robot_cov, float)
    m = x.shape[0]
    B = scene.T_SO_nominal @ _pose_matrices(x)
    A = scene.Z @ B @ np.linalg.inv(scene.X)
    pb = JointProblem(bench, param, np.zeros((m, 1)), A, scene.T_SO_nominal, robot_cov, True, measurement)
    theta = np.zeros(param.k)
    model = pb.model(theta)
    res = model.evaluate(x, check_range=False)
    pb.z = res.z
    pb.m = res.z.shape[1]
    S, Jt = pb.jacobians(theta, x, res.uv)
    I = pose_information(S, Jt, B, x, scene.X, robot_cov)
    I[~res.valid] = 0.0
    return I, res.valid


def _pose_matrices(x):
    from ..optics.pose import pose_to_matrix

    return pose_to_matrix(x)


def predicted_joint_uncertainty(bench, param: LensParameterisation, scene, x, robot_cov=None,
                                measurement=None) -> dict:
    """Predicted Z 1-sigma (joint CRLB, theta free) for lens poses x (n, 6) and, for
    comparison, with theta known (poses that do not light the pupil for the mean
    as-built lens count for nothing; n_lit says how many do): keys Z_sigma_mm (3), Z_sigma_deg (3), Z_translation_mm /
    Z_rotation_deg (RMS norms), *_known_lens_*, theta_sigma (posterior, prior = 1), cov."""
    I, lit = candidate_information(bench, param, scene, x, robot_cov, measurement)
    return {**z_sigma(I.sum(axis=0) + theta_prior(param.k)), "n_lit": int(lit.sum())}


@dataclass(frozen=True)
class JointDesign:
    """Chosen poses x (n, 6) (mm, rad, relative to nominal), flange poses A (n, 4, 4),
    chosen / random: predicted_joint_uncertainty-like dicts (random: the same for the
    given comparison plan), exchanges made."""

    x: np.ndarray
    A: np.ndarray
    chosen: dict
    random: dict | None
    exchanges: int


def _reachable(scene, x) -> bool:
    from ..errors import PoseRangeError
    from .robot import flange_pose

    try:
        flange_pose(scene, x[None], check_reach=True)
        return True
    except PoseRangeError:
        return False


def design_joint_poses(bench, param: LensParameterisation, scene, n: int, candidates, *, compare=None,
                       robot_cov=None, check_reach: bool = True, max_passes: int = 10) -> JointDesign:
    """Ds-optimal (for Z) choice of n lens poses among candidates (m, 6) for the joint
    calibration; compare: a plan (n', 6) whose predicted uncertainty is reported beside."""
    from .robot import flange_pose

    if n < 3:
        raise ConfigError(f"n: the joint calibration needs at least 3 poses, got {n}")
    cand = np.atleast_2d(np.asarray(candidates, float))
    I, lit = candidate_information(bench, param, scene, cand, robot_cov)
    usable = lit.copy()
    swaps = 0
    while True:
        idx = np.flatnonzero(usable)
        if idx.size < 1:
            raise ConfigError("candidates: none lights the pupil and is reachable; choose poses nearer nominal")
        chosen, F, eps, sw = select_ds(I[idx], param.k, n, max_passes)
        swaps += sw
        x = cand[idx[chosen]]
        if not check_reach:
            break
        bad = [i for i in sorted(set(chosen)) if not _reachable(scene, cand[idx[i]])]
        if not bad:
            break
        usable[idx[bad]] = False  # unreachable: drop and choose again
    A = flange_pose(scene, x, check_reach=False)
    rand = predicted_joint_uncertainty(bench, param, scene, compare, robot_cov) if compare is not None else None
    return JointDesign(x=x, A=A, chosen=z_sigma(F - eps), random=rand, exchanges=swaps)
