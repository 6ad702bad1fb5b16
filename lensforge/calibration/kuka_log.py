"""KUKA ``$POS_ACT`` logs: the flange pose as the controller reports it, one row per record.

``$POS_ACT`` (KUKA System Software, read e.g. remotely over OpenShowVar) is an E6POS:
X, Y, Z in mm and A, B, C in degrees (R = Rz(A) Ry(B) Rx(C)) of the TCP in ``$BASE``,
plus S (status) and T (turn), which pick the arm configuration and do not change the
pose. It is the flange pose ^W T_E only when ``$TOOL = $NULLFRAME`` (TCP = flange) and
``$BASE = $NULLFRAME`` (robot root), as the plan's KRL program sets them.

Layout read (``read_kuka_log``; UTF-8/cp1252, LF/CRLF; ``#`` comment lines): a CSV header,
then one row per record, with either

- columns ``X,Y,Z,A,B,C`` (any order, any case; ``S``, ``T``, ``E1``.. and unknown
  columns are kept out of the pose), or
- one column ``POS_ACT`` (or ``$POS_ACT``) holding the controller's text
  ``{E6POS: X 1.0, Y 2.0, Z 3.0, A 0.0, B 90.0, C 0.0, S 6, T 27, E1 0.0, ...}``;

and a pose id: a ``pose`` column (matched to the WFS ids as integers when both are), or a
``time`` column (ISO 8601, or seconds) matched to the WFS files' times by
``assign_by_time`` (the nearest record within ``max_dt_s``; a WFS export's time is its
file modification time unless given). A ``# tool:`` or ``# base:`` comment other than
``$NULLFRAME``/``flange`` is an error: the log is then not the flange pose.
"""

from __future__ import annotations

import csv
import io
import math
import re
from datetime import datetime
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .thorlabs import read_text_any

__all__ = ["read_kuka_log", "parse_e6pos", "assign_by_time", "MAX_DT_S"]

MAX_DT_S = 5.0  # ASSUMPTION: a record within 5 s of a WFS frame belongs to it (the plan settles 2 s per pose)
_FIELD = re.compile(r"\b([A-Z][A-Z0-9]?)\s+([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)")


def parse_e6pos(text: str) -> dict:
    """{name: value} of a KRL E6POS/POS/FRAME aggregate text ``{E6POS: X 1.0, Y 2, ...}``."""
    body = text.strip().strip('"')
    if "{" in body:
        body = body[body.index("{") + 1:body.rindex("}") if "}" in body else None]
    if ":" in body:
        body = body.split(":", 1)[1]
    return {k: float(v) for k, v in _FIELD.findall(body.upper())}


def _time(path, no, text):
    t = text.strip()
    try:
        return float(t)
    except ValueError:
        pass
    try:
        return datetime.fromisoformat(t.replace("Z", "+00:00")).timestamp()
    except ValueError:
        raise ConfigError(f"{path}: row {no}, field time: {t!r} is neither seconds nor an ISO 8601 time") from None


def read_kuka_log(path) -> dict:
    """Records of a ``$POS_ACT`` log (module docstring): {"ids": (n,), "xyzabc": (n, 6) mm and
    deg, "rows": line numbers, "times": (n,) s when the log has a time column and no pose
    column (ids are then "t<row>" until ``assign_by_time``) else None, "status_turn": (n, 2)
    S and T (NaN where not logged)}. ``formats.read_robot_poses`` (format ``kuka_log``)
    turns it into a PoseTable."""
    path = Path(path)
    text = read_text_any(path, "robot poses file")
    lines = [(no, ln) for no, ln in enumerate(text.split("\n"), start=1) if ln.strip()]
    data = []
    for no, ln in lines:
        s = ln.strip()
        if s.startswith("#"):
            body = s.lstrip("#").strip().lower()
            for key in ("tool", "base"):
                if body.startswith(key + ":"):
                    v = body.split(":", 1)[1].strip().replace(" ", "")
                    if v not in ("$nullframe", "nullframe", "flange", "robotroot", "{x0,y0,z0,a0,b0,c0}"):
                        raise ConfigError(f"{path}: row {no}, field {key}: {v!r}; $POS_ACT is the flange pose "
                                          f"only with ${key.upper()} = $NULLFRAME; log with ${key.upper()} = "
                                          "$NULLFRAME (as the plan's KRL program sets)")
            continue
        data.append((no, s))
    if len(data) < 2:
        raise ConfigError(f"{path}: no records; expected a CSV header (pose or time, X,Y,Z,A,B,C or POS_ACT) and rows")
    hno, hline = data[0]
    delim = ";" if hline.count(";") > hline.count(",") else ","
    rows = list(csv.reader(io.StringIO("\n".join(s for _, s in data)), delimiter=delim))
    head = [h.strip().lstrip("$").lower() for h in rows[0]]
    col = {h: i for i, h in enumerate(head)}
    has_xyz = all(c in col for c in "xyzabc")
    if not has_xyz and "pos_act" not in col:
        raise ConfigError(f"{path}: row {hno}, header: expected columns X,Y,Z,A,B,C or a POS_ACT column, "
                          f"got {hline!r}")
    id_col = col.get("pose", col.get("id"))
    t_col = col.get("time", col.get("timestamp"))
    if id_col is None and t_col is None:
        raise ConfigError(f"{path}: row {hno}, header: no 'pose' or 'time' column; log the pose id or the time "
                          "of each record")
    ids, vals, nos, times, st = [], [], [], [], []
    for (no, _), f in zip(data[1:], rows[1:]):
        if len(f) < len(head):
            raise ConfigError(f"{path}: row {no}: {len(f)} fields, expected {len(head)} ({hline})")
        if has_xyz:
            v = {}
            for c in "xyzabc":
                t = f[col[c]].strip()
                if re.fullmatch(r"[+-]?\d+,\d+", t):
                    raise ConfigError(f"{path}: row {no}, field {c.upper()}: {t!r} uses a decimal comma; "
                                      "log with a decimal point")
                try:
                    v[c.upper()] = float(t)
                except ValueError:
                    raise ConfigError(f"{path}: row {no}, field {c.upper()}: {t!r} is not a number") from None
            for c in "st":
                if c in col:
                    try:
                        v[c.upper()] = float(f[col[c]])
                    except ValueError:
                        pass
        else:
            v = parse_e6pos(f[col["pos_act"]])
            miss = [c for c in "XYZABC" if c not in v]
            if miss:
                raise ConfigError(f"{path}: row {no}, field POS_ACT: {', '.join(miss)} missing in "
                                  f"{f[col['pos_act']]!r}")
        x = [v[c] for c in "XYZABC"]
        if not all(math.isfinite(a) for a in x):
            raise ConfigError(f"{path}: row {no}: a pose value is not finite")
        vals.append(x)
        st.append([v.get("S", np.nan), v.get("T", np.nan)])
        nos.append(no)
        if id_col is not None:
            ids.append(f[id_col].strip())
        else:
            ids.append(f"t{no}")
        if t_col is not None:
            times.append(_time(path, no, f[t_col]))
    seen = {}
    for i, no in zip(ids, nos):
        if not i:
            raise ConfigError(f"{path}: row {no}, field pose: empty pose id")
        if i in seen:
            raise ConfigError(f"{path}: row {no}, field pose: duplicate pose id {i!r} (first at row {seen[i]})")
        seen[i] = no
    return {"ids": tuple(ids), "xyzabc": np.array(vals), "rows": tuple(nos),
            "times": np.array(times) if (times and id_col is None) else None, "status_turn": np.array(st)}


def assign_by_time(log, wfs_times: dict, max_dt_s: float = MAX_DT_S):
    """The log's PoseTable (``formats.PoseTable`` with times) renamed by the WFS pose ids: for
    each id (time in s) the nearest record within max_dt_s. ConfigError when a record would
    serve two ids or none is near."""
    from dataclasses import replace

    t = getattr(log, "times", None)
    if t is None:
        raise ConfigError(f"{log.source}: no time column to match the WFS files' times")
    ids, idx = [], []
    used = {}
    for i, ti in wfs_times.items():
        k = int(np.argmin(np.abs(t - ti)))
        if abs(t[k] - ti) > max_dt_s:
            continue  # reported by the session matcher as a pose without a robot pose
        if k in used:
            raise ConfigError(f"{log.source}: row {log.rows[k]}: the record nearest to both pose {used[k]} and "
                              f"pose {i}; log one record per pose")
        used[k] = i
        ids.append(str(i))
        idx.append(k)
    if not idx:
        raise ConfigError(f"{log.source}: field time: no record within {max_dt_s:g} s of any WFS file's time")
    return replace(log, ids=tuple(ids), T=log.T[idx], rows=tuple(log.rows[k] for k in idx), times=None)
