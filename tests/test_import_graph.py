"""The package's import graph runs one way: no cycles, and no module imports another
module's private (``_x``) names. Checked statically with ``ast`` over every module,
including imports inside functions."""

from __future__ import annotations

import ast
from pathlib import Path

import lensforge

ROOT = Path(lensforge.__file__).parent


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path):
    """(target module, imported names) for every lensforge import in a file."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "lensforge":
                continue
            yield target, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "lensforge":
                    yield a.name, []


def _graph():
    modules = {_module_name(p): p for p in ROOT.rglob("*.py")}
    edges: dict[str, set[str]] = {m: set() for m in modules}
    private = []
    for mod, path in modules.items():
        for target, names in _imports(path):
            for n in names:
                sub = f"{target}.{n}"
                if sub in modules:  # "from pkg import module"
                    edges[mod].add(sub)
                elif n.startswith("_") and not n.startswith("__"):
                    private.append(f"{mod}: from {target} import {n}")
            if target in modules and target != mod:
                if not names or any(f"{target}.{n}" not in modules for n in names):
                    edges[mod].add(target)
    return modules, edges, private


def test_no_private_names_cross_modules():
    _, _, private = _graph()
    assert private == []


def test_no_import_cycles():
    modules, edges, _ = _graph()
    # a package's __init__ importing its own submodules is not a cycle of the code
    for m in modules:
        edges[m] = {t for t in edges[m] if not (t.startswith(m + ".") and modules[m].name == "__init__.py")}
    state: dict[str, int] = {}
    cycles = []

    def visit(m, stack):
        state[m] = 1
        stack.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                cycles.append(" -> ".join(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t, stack)
        stack.pop()
        state[m] = 2

    for m in sorted(modules):
        if m not in state:
            visit(m, [])
    assert cycles == []
