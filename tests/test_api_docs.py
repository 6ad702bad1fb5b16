"""The API page and the numpydoc sections of every exported name (issue 20, item 5)."""

import importlib.util
import inspect
from pathlib import Path

import lensforge as lf

ROOT = Path(__file__).resolve().parents[1]


def _make_api():
    spec = importlib.util.spec_from_file_location("make_api", ROOT / "docs" / "make_api.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _documented_names(lines):
    names = set()
    for line in lines:
        if line.strip() and not line.startswith((" ", "\t")):
            head = line.split(" : ")[0]
            names |= {n.strip().lstrip("*") for n in head.split(",")}
    return names


def test_api_page_is_up_to_date():
    make_api = _make_api()
    assert (ROOT / "docs" / "api.md").read_text() == make_api.render(), "run: python docs/make_api.py"


def test_every_exported_callable_has_numpydoc_sections_naming_its_parameters():
    make_api = _make_api()
    problems = []
    for name in lf.__all__:
        if name == "__version__":
            continue
        obj = getattr(lf, name)
        if not (inspect.isfunction(obj) or inspect.isclass(obj)):
            continue
        _, sections = make_api.split_sections(inspect.getdoc(obj) or "")
        if inspect.isclass(obj) and issubclass(obj, BaseException):
            if "Parameters" not in sections:
                problems.append(f"{name}: no Parameters")
            continue
        params = [p for p in inspect.signature(obj).parameters.values()
                  if p.name not in ("self", "cls") and not p.name.startswith("_")]
        if params and "Parameters" not in sections:
            problems.append(f"{name}: no Parameters")
            continue
        undocumented = {p.name for p in params} - _documented_names(sections.get("Parameters", []))
        if undocumented:
            problems.append(f"{name}: Parameters lacks {sorted(undocumented)}")
        if inspect.isfunction(obj) and "Returns" not in sections:
            problems.append(f"{name}: no Returns")
    assert not problems, problems
