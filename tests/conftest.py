import numpy as np
import pytest
from threadpoolctl import threadpool_limits

import lensforge as lf

# one BLAS thread per test worker, as the CLI (pytest -n 2 on two cores: threaded BLAS in each worker
# oversubscribes them; a 'cells' pose evaluation took 1.8x the CPU)
_ONE_BLAS_THREAD = threadpool_limits(limits=1)


@pytest.fixture(scope="session")
def bench():
    return lf.Bench.default()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def check_json_output(command, stdout):
    """Validate a command's ``--json`` stdout against its documented schema (docs/json.md);
    returns the parsed object."""
    import json

    data = json.loads(stdout)
    try:
        import jsonschema
    except ImportError:  # the test extra installs it; without it only the JSON itself is checked
        return data
    from lensforge.schemas import load_schema

    jsonschema.validate(data, load_schema(command))
    return data


def run_cli(*args, cwd=None):
    """Run ``python -m lensforge ARGS`` in a subprocess (stdout, stderr, returncode). A
    successful ``--json`` run is checked against the command's JSON schema on the way."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "lensforge", *map(str, args)], capture_output=True, text=True,
                       timeout=300, cwd=cwd)
    from lensforge.schemas import COMMANDS

    if r.returncode == 0 and "--json" in args and args and args[0] in COMMANDS:
        check_json_output(args[0], r.stdout)
    return r


def run_cli_inprocess(monkeypatch, capsys, *args):
    """Run the CLI in this process (shares traced kernels): (exit code, stdout, stderr)."""
    import sys

    from lensforge.cli import main

    monkeypatch.setattr(sys, "argv", ["lensforge", *map(str, args)])
    code = 0
    try:
        main()
    except SystemExit as e:
        code = e.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="session")
def perfect_sessions(tmp_path_factory):
    """Five honest bench sessions of the extended-polynomial paper lens exactly as designed (8
    planned poses, one plan, seeds 100..104), written as a real session's files: a list of
    {file name: Path} (robot_poses.csv, wfs_zernike.csv, truth.json). Shared by the model-check
    and mistake tests (issue 23)."""
    from lensforge.calibration import formats
    from lensforge.calibration.session import load_design_lens, plan
    from lensforge.verification.session_sim import simulate_session

    lens, bench = load_design_lens("paper:extended_polynomial")
    p = plan(lens, bench=bench, n=8, seed=0, tolerances="none")
    out = []
    for seed in range(5):
        s = simulate_session(lens, tolerances=None, seed=100 + seed, bench=bench, session_plan=p)
        out.append(formats.write_bundle(tmp_path_factory.mktemp(f"session{seed}"), s.files()))
    return out


@pytest.fixture(scope="module")
def polynomial_joint_setup():
    """(bench, lens, scene, plan) of the joint-calibration tests: the paper's polynomial lens
    (all six pose DOF observable per pose: a well conditioned joint problem) on the default
    bench, the paper scene and the study's 12-pose plan."""
    from lensforge.calibration.robot import paper_scene
    from lensforge.optics.bench import Bench
    from lensforge.optics.lens import paper_lens
    from lensforge.verification.study import StudyConfig, calibration_plan

    bench = Bench.default()
    return bench, paper_lens("polynomial"), paper_scene(bench.placement.distance_mm), \
        calibration_plan(StudyConfig(n_poses=12))


def pose_error(T_true, T_est):
    """The pose vector (mm, rad) of T_true^-1 T_est."""
    from lensforge.optics.pose import matrix_to_pose

    return matrix_to_pose(np.linalg.solve(T_true, T_est))



def assert_exact_transforms(pairs, rtol=1e-8):
    """Noise-free exactness of estimated transforms: for each (true, estimated) 4x4 pair the
    translation error is within rtol of the true translation and the rotation error within rtol rad."""
    for T_true, T_est in pairs:
        e = pose_error(T_true, T_est)
        assert np.linalg.norm(e[:3]) <= rtol * np.linalg.norm(T_true[:3, 3])
        assert np.linalg.norm(e[3:]) <= rtol