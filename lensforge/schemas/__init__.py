"""JSON schemas (draft 2020-12) of every ``lensforge COMMAND --json`` output.

One file per command, ``<command>.schema.json``, next to this module; ``docs/json.md``
is rendered from them (:func:`render_markdown`). The schemas list the keys a user can
rely on within a ``schema_version``; outputs may carry more keys (``additionalProperties``).
lensforge does not need ``jsonschema`` at run time; the test suite validates outputs with it.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

__all__ = ["COMMANDS", "load_schema", "render_markdown", "resolve_ref"]

COMMANDS = ("evaluate", "design", "plot", "compare", "export", "estimate", "estimate-study", "scenario", "handeye",
            "plan", "calibrate", "simulate-session", "study", "budget")


def load_schema(command: str) -> dict[str, Any]:
    """The JSON schema of ``lensforge COMMAND --json`` (KeyError for a command without one)."""
    if command not in COMMANDS:
        raise KeyError(f"no --json schema for command {command!r}; commands: {', '.join(COMMANDS)}")
    return json.loads(resources.files(__name__).joinpath(f"{command}.schema.json").read_text())


def _type(p: dict) -> str:
    t = p.get("type", "any" if "const" not in p else f"const {p['const']}")
    return " or ".join(t) if isinstance(t, list) else str(t)


def resolve_ref(p: dict, root: dict) -> dict:
    """p with a local ``$ref`` (``#/$defs/NAME``) merged in; p's own keys (description) win."""
    ref = p.get("$ref")
    if not ref:
        return p
    target = root
    for part in ref.removeprefix("#/").split("/"):
        target = target[part]
    return {**target, **{k: v for k, v in p.items() if k != "$ref"}}


def _rows(props: dict, required: list, root: dict, prefix: str = "") -> list[str]:
    out = []
    for k, p in props.items():
        name = f"{prefix}{k}"
        p = resolve_ref(p, root)
        out.append(f"| `{name}` | {_type(p)} | {'yes' if k in required else 'no'} | {p.get('description', '')} |")
        if p.get("type") == "object" and p.get("properties"):
            out += _rows(p["properties"], p.get("required", []), root, name + ".")
        items = p.get("items")
        if isinstance(items, dict) and items.get("properties"):
            out += _rows(items["properties"], items.get("required", []), root, name + "[].")
        extra = p.get("additionalProperties")
        if isinstance(extra, dict) and extra.get("properties"):
            out += _rows(extra["properties"], extra.get("required", []), root, name + ".<name>.")
    return out


def render_markdown() -> str:
    """docs/json.md: one table of keys per command."""
    lines = ["# `--json` outputs", "",
             "Every command that reports numbers has `--json`: the keys below go to stdout (human text goes",
             "to stderr). Units are in the key names or the descriptions. Keys are only added within a",
             "`schema_version`; the machine-readable schemas are `lensforge/schemas/<command>.schema.json`",
             "(`lensforge.schemas.load_schema(command)`). This page is rendered from them by",
             "`lensforge.schemas.render_markdown()`.", ""]
    for c in COMMANDS:
        s = load_schema(c)
        lines += [f"## `lensforge {c} --json`", "", s.get("description", ""), "",
                  "| key | type | always | meaning |", "| --- | --- | --- | --- |",
                  *_rows(s["properties"], s.get("required", []), s), ""]
    return "\n".join(lines)
