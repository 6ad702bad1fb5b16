"""The library surface: top-level names resolve, carry type hints, and the package is typed."""

import inspect
from pathlib import Path

import numpy as np

import lensforge as lf

def _callables():
    """Every public callable: top-level functions and the public methods of top-level classes,
    and each CLI command's library function (lensforge/commands/*.py)."""
    from lensforge.cli import _COMMANDS

    for name, fn in _COMMANDS.items():
        yield f"lensforge {name}", fn
    for name in lf.__all__:
        if name == "__version__":
            continue
        obj = getattr(lf, name)
        if inspect.isfunction(obj):
            yield name, obj
        elif inspect.isclass(obj):
            for k, v in vars(obj).items():
                if inspect.isfunction(v) and not k.startswith("_"):
                    yield f"{name}.{k}", v


def test_every_public_name_resolves_and_is_annotated():
    missing = []
    for name, fn in _callables():
        sig = inspect.signature(fn)
        for p, v in sig.parameters.items():
            if p in ("self", "cls") or v.kind in (v.VAR_POSITIONAL, v.VAR_KEYWORD):
                continue
            if v.annotation is inspect.Parameter.empty:
                missing.append(f"{name}({p})")
        if sig.return_annotation is inspect.Signature.empty:
            missing.append(f"{name} -> ?")
    assert not missing, missing


def test_library_functions_of_the_workflow_are_exported():
    """The functions behind design, study, budget and the bench commands are top-level names."""
    for name in ("optimize_design", "verify", "tolerance_budget", "sensitivity_analysis", "plan", "calibrate",
                 "estimate", "simulate_session", "read_wfs", "read_robot_poses", "resolve_lens", "LensSpec"):
        assert name in lf.__all__, name


def test_package_is_typed():
    import tomllib

    assert (Path(lf.__file__).parent / "py.typed").exists()
    pyproject = Path(lf.__file__).resolve().parents[1] / "pyproject.toml"
    data = tomllib.loads(pyproject.read_text())["tool"]["setuptools"]["package-data"]
    assert "py.typed" in data["lensforge"] and "*.schema.json" in data["lensforge.schemas"]


def test_zernike_and_pose_helpers_at_top_level_round_trip():
    for j in range(1, 40):
        assert lf.osa_to_noll(lf.noll_to_osa(j)) == j
        assert lf.thorlabs_to_noll(lf.noll_to_thorlabs(j)) == j
        assert lf.nm_to_noll(*lf.noll_to_nm(j)) == j
    assert lf.noll_to_osa(4) == 4 and lf.noll_to_osa(2) == 2 and lf.noll_to_thorlabs(1) == 1  # defocus, tilt x, piston
    x = np.array([1.0, -2.0, 3.0, 0.1, -0.2, 0.3])
    tol = 64 * np.finfo(float).eps * np.abs(x).max()  # round-off of a few 3x3 products, any BLAS kernel
    np.testing.assert_allclose(lf.matrix_to_pose(lf.pose_to_matrix(x)), x, atol=tol)
    T = lf.pose_to_matrix(x)
    np.testing.assert_allclose(lf.invert_poses(T) @ T, np.eye(4), atol=tol)


def test_no_module_re_exports_another_modules_names():
    """A module's __all__ lists what it defines: a function or class named there lives there
    (an importer goes to the defining module; only the package's lazy top level gathers names)."""
    import importlib
    import pkgutil

    found = []
    for m in pkgutil.walk_packages(lf.__path__, "lensforge."):
        if m.name.endswith("__main__"):
            continue
        mod = importlib.import_module(m.name)
        for name in getattr(mod, "__all__", ()):
            if not hasattr(mod, name):
                found.append(f"{mod.__name__}.{name} (listed in __all__, not defined)")
                continue
            obj = getattr(mod, name)
            if (inspect.isfunction(obj) or inspect.isclass(obj)) and obj.__module__ != mod.__name__:
                found.append(f"{mod.__name__}.{name} (defined in {obj.__module__})")
    for mod_name, name in (("lensforge.optics.bench", "write_atomic"), ("lensforge.calibration.session", "SCHEMA_VERSION")):
        if name in importlib.import_module(mod_name).__all__:
            found.append(f"{mod_name}.{name}")
    assert not found, found


def test_type_checking_imports_are_exactly_the_lazy_exports():
    """lensforge/__init__.py's one source of names is ``_EXPORTS`` (``__all__`` is built from it);
    the TYPE_CHECKING imports that type checkers read must name the same objects from the same
    modules, no more and no fewer."""
    import ast

    src = Path(lf.__file__).read_text()
    tree = ast.parse(src)
    block = next(n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING")
    seen = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1, ast.unparse(node)
        for alias in node.names:
            assert alias.asname is None, ast.unparse(node)
            seen[alias.name] = f"lensforge.{node.module}"
    assert seen == lf._EXPORTS
    assert sorted(lf.__all__) == sorted([*lf._EXPORTS, "__version__"])
