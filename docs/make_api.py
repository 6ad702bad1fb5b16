"""Write docs/api.md, the API page, from the docstrings of the names ``lensforge`` exports.

Run: python docs/make_api.py          (writes docs/api.md)
     python docs/make_api.py --check  (exit 1 when docs/api.md is out of date)

No sphinx: ``inspect`` gives each name's signature and docstring, and the numpydoc
sections (Parameters, Returns, Raises, ...) become Markdown lists. The page follows the
order of ``lensforge._EXPORTS`` (grouped by the module that defines each name), so it
reads like the package's own table of contents. tests/test_api_docs.py checks that the
page is up to date and that every exported callable has its sections.
"""

from __future__ import annotations

import inspect
import re
import sys
from pathlib import Path

API_MD = Path(__file__).with_name("api.md")
SECTIONS = ("Parameters", "Returns", "Yields", "Raises", "Warns", "Attributes", "See Also", "Notes", "Examples")
LIST_SECTIONS = {"Parameters", "Returns", "Yields", "Raises", "Warns", "Attributes"}


def split_sections(doc: str) -> tuple[str, dict[str, list[str]]]:
    """A numpydoc docstring (already ``inspect.cleandoc``-ed) as (prose, {section: lines})."""
    lines = doc.splitlines()
    prose: list[str] = []
    sections: dict[str, list[str]] = {}
    current: list[str] = prose
    i = 0
    while i < len(lines):
        line = lines[i]
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() in SECTIONS and nxt.strip() and set(nxt.strip()) == {"-"}:
            current = sections.setdefault(line.strip(), [])
            i += 2
            continue
        current.append(line)
        i += 1
    return "\n".join(prose).strip(), sections


def _entries(lines: list[str]) -> list[tuple[str, str]]:
    """(head, description) pairs of a list section: a head at indent 0, its text indented."""
    out: list[tuple[str, list[str]]] = []
    for line in lines:
        if not line.strip():
            continue
        if not line.startswith((" ", "\t")):
            out.append((line.strip(), []))
        elif out:
            out[-1][1].append(line.strip())
    return [(h, " ".join(d)) for h, d in out]


def _head(head: str) -> str:
    if " : " in head:
        name, typ = head.split(" : ", 1)
        return f"`{name.strip()}` (*{typ.strip()}*)"
    return f"*{head}*"


def _annotation(a) -> str:
    if a is inspect.Parameter.empty:
        return ""
    return a if isinstance(a, str) else inspect.formatannotation(a)


def _signature(obj) -> str:
    """(a: T = default, ...) -> R with the annotations as written (the package uses
    ``from __future__ import annotations``: they are strings) and no memory addresses."""
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return ""
    parts, star_done = [], False
    params = list(sig.parameters.values())
    for i, prm in enumerate(params):
        if prm.name.startswith("_"):  # a private argument is not part of the documented interface
            continue
        if prm.kind is prm.KEYWORD_ONLY and not star_done:
            parts.append("*")
            star_done = True
        text = {prm.VAR_POSITIONAL: "*", prm.VAR_KEYWORD: "**"}.get(prm.kind, "") + prm.name
        if prm.kind is prm.VAR_POSITIONAL:
            star_done = True
        ann = _annotation(prm.annotation)
        if ann:
            text += f": {ann}"
        if prm.default is not inspect.Parameter.empty:
            text += (" = " if ann else "=") + re.sub(r" at 0x[0-9a-f]+", "", repr(prm.default))
        parts.append(text)
        if prm.kind is prm.POSITIONAL_ONLY and (i + 1 == len(params) or params[i + 1].kind is not prm.POSITIONAL_ONLY):
            parts.append("/")
    ret = _annotation(sig.return_annotation)
    return f"({', '.join(parts)})" + (f" -> {ret}" if ret else "")


def render_name(name: str, obj) -> str:
    """The Markdown block of one exported name."""
    kind = "class" if inspect.isclass(obj) else "function" if callable(obj) else "constant"
    out = [f"### `lensforge.{name}`", ""]
    if kind == "constant":
        value = repr(obj)
        if len(value) > 300:
            value = f"{type(obj).__name__} with {len(obj)} entries: {', '.join(map(str, list(obj)[:8]))}"
        out += [f"Constant (defined in `{_module_of(name)}`): `{value}`", ""]
        return "\n".join(out)
    sig = _signature(obj)
    out += ["```python", f"{'class ' if kind == 'class' else ''}{name}{sig}", "```", ""]
    prose, sections = split_sections(inspect.getdoc(obj) or "")
    if prose:
        out += [prose, ""]
    for sec in SECTIONS:
        if sec not in sections:
            continue
        out += [f"**{sec}**", ""]
        if sec in LIST_SECTIONS:
            for head, desc in _entries(sections[sec]):
                out.append(f"- {_head(head)}" + (f": {desc}" if desc else ""))
        else:
            out.append("\n".join(sections[sec]).strip())
        out.append("")
    return "\n".join(out)


def _module_of(name: str) -> str:
    import lensforge

    return lensforge._EXPORTS[name]


def render() -> str:
    """The whole API page."""
    import lensforge

    head = inspect.cleandoc(lensforge.__doc__ or "")
    out = ["# lensforge API", "",
           "<!-- Generated by docs/make_api.py from the docstrings; do not edit by hand. -->", "",
           head, "",
           "Every name below is importable as `import lensforge as lf; lf.NAME` (resolved lazily).", ""]
    by_module: dict[str, list[str]] = {}
    for name, mod in lensforge._EXPORTS.items():
        by_module.setdefault(mod, []).append(name)
    anchors, seen = {}, {}
    for names in by_module.values():  # GitHub's heading ids: lower case, dots dropped, repeats get -1, -2, ...
        for n in names:
            base = f"lensforge{n.lower()}"
            anchors[n] = base + (f"-{seen[base]}" if base in seen else "")
            seen[base] = seen.get(base, 0) + 1
    out += ["## Contents", ""]
    for mod, names in by_module.items():
        out.append(f"- `{mod}`: " + ", ".join(f"[`{n}`](#{anchors[n]})" for n in names))
    out.append("")
    for mod, names in by_module.items():
        out += [f"## `{mod}`", ""]
        doc = inspect.getdoc(sys.modules.get(mod) or __import__(mod, fromlist=["_"]))
        if doc:
            out += [doc.split("\n\n")[0].strip(), ""]
        for name in names:
            out.append(render_name(name, getattr(lensforge, name)))
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str]) -> int:
    text = render()
    if "--check" in argv:
        if not API_MD.exists() or API_MD.read_text() != text:
            print(f"{API_MD} is out of date: run python docs/make_api.py", file=sys.stderr)
            return 1
        return 0
    API_MD.write_text(text)
    print(f"wrote {API_MD}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
