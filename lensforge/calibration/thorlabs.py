"""Files the Thorlabs WFS instrument writes: the WFS software's measurement exports and
the driver's (SDK) spot-deviation fields, one file per pose.

Layouts (from public sources: the issue that introduced this module cites them):

**WFS software export** (``read_export``; one text file per measurement):

- a free-text header block; a line whose key holds ``Wavelength`` (``Wavelength [nm]:
  532`` or ``Wavelength [nm],532``) gives the wavelength (nm, or um when the key says
  ``[um]``/``[µm]``);
- sections introduced by ``*** NAME ***`` lines, each ending where the next ``***`` line
  starts. Read: ``*** ZERNIKE FIT ***`` (required), a header row ``Index,Order,
  Frequency,Coefficient [µm]`` and one row per mode with its explicit radial order n and
  signed frequency m (OSA/ANSI sequence, Thorlabs index = OSA j + 1, piston included).
  The modes are taken by (n, m), never by position; ``*** PUPIL ***`` rows ``Centroid X
  [mm]``, ``Centroid Y [mm]``, ``Diameter X [mm]``, ``Diameter Y [mm]`` (a circular pupil:
  both diameters equal). Every other section (``*** BEAM ***``, the Fourier/optometric
  block, ``*** WAVEFRONT ***`` with its ``y / x [mm]`` grid) and every unknown line are
  skipped.
- encoding UTF-8, cp1252 or latin-1 (the µ), LF or CRLF line ends; separators ``,``,
  ``;`` or tab. Comma decimals (``0,123``: a German Windows locale) are refused with the
  setting to change.

**SDK spot fields** (``read_spot_field``; one CSV or NPZ per pose): per-lenslet spot
deviations in pixels from ``WFS_GetSpotDeviations`` (arrays [Y][X], NaN where no spot
was found) and the device's MLA data from ``WFS_GetMlaData`` (lenslet focal length and
pitch in um, camera pixel pitch in um) plus the centre of the lenslet grid in {S} (mm).
A lenslet (iy, ix) sits at x = (ix - (nx - 1)/2) pitch + cx, y = (iy - (ny - 1)/2) pitch
+ cy in {S}; its slope is deviation * pixel pitch / focal length (rad). ASSUMPTION: row
iy and the y deviation run along +y of {S} (the Thorlabs WFS convention of DESIGN.md,
+y up); a driver that delivers image rows top-down must have its rows flipped
(``numpy.flipud``) and its y deviations negated before saving.

- NPZ: arrays ``deviation_x_px`` and ``deviation_y_px`` (ny, nx), scalars
  ``focal_length_um``, ``lenslet_pitch_um``, ``pixel_pitch_um``, ``center_offset_mm``
  (2,), optional ``wavelength_nm``, ``pupil_center_mm`` (2,), ``pupil_radius_mm``,
  ``reference_pose`` (a string: the deviations are relative to a user reference spot
  field recorded at that pose, ``WFS_SetSpotsToUserReference``), ``tilt_cancelled``.
- CSV: ``# key: value`` lines with the same scalars (``# center_offset_mm: 0.0, 0.0``),
  then a header ``iy,ix,dx_px,dy_px`` and one row per lenslet (``nan`` or an empty cell
  for a missing spot).

Which instrument settings give a usable file (WFS software "Setup" / the SDK calls):
wavelength = the laser's (``WFS_SetWavelength``); circular pupil centred and sized as the
bench's ``sensor.pupil_center_mm``/``pupil_radius_mm`` (``WFS_SetPupil``); Zernike fit up to
at least the bench's ``sensor.zernike_order``; wavefront unit um; **tilt cancel OFF**
(``WFS_CalcSpotToReferenceDeviations(cancelWavefrontTilt = 0)``; Thorlabs' own sample
calls it with 1, which zeroes the tilt modes and the mean spot deviation that carry the
lens pose's translation): a file whose tilt is zero in every pose is refused naming that
setting; reference "internal" (the lenslet centres) unless a user reference is recorded
at one of the session's poses and named (``reference_pose``), see ``measurement``.
"""

from __future__ import annotations

import glob as _glob
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..input_checks import field_number
from ..fileio import MAX_TABLE_BYTES, read_bounded
from ..optics.zernike import nm_to_noll, noll_to_osa

__all__ = ["read_text_any", "read_export", "export_text", "read_export_folder", "pose_id_from_name",
           "expand_measurements", "SpotFields", "read_spot_field", "read_spot_fields", "spot_field_csv",
           "spot_field_npz", "check_tilt_not_cancelled", "check_not_all_zero", "POSE_ID_PATTERN",
           "PUPIL_TOL_MM", "TILT_ZERO_UM"]

POSE_ID_PATTERN = r"(\d+)(?!.*\d)"  # the last integer in a file name: pose_07.csv -> 7
# ASSUMPTION: tolerances of a header against the bench. The software prints 3 decimals
# (nm, mm); a laser line is known to well under 0.5 nm; 5 um is 1/30 lenslet pitch.
PUPIL_TOL_MM = 0.005  # the software prints the pupil to 0.01 mm (checked against the bench by plausibility)
# |tilt| below this in every pose (um) = cancelled (a lens 20 mm off the sensor tilts
# the wavefront by ~1e-2 um per um of decentre: a real tilt is far above rounding)
TILT_ZERO_UM = 1e-9
TILT_ZERO_PX = 1e-9  # mean spot deviation (px) treated as exactly zero


# ----------------------------------------------------------------------------- text


def read_text_any(path: Path, what: str) -> str:
    """Text of a file written on Windows or elsewhere: UTF-8 (BOM allowed), else cp1252,
    else latin-1; CRLF/CR line ends become LF. Bounded (``fileio.read_bounded``): /dev/zero or a
    huge file is refused, never read whole."""
    try:
        raw = read_bounded(path, what, MAX_TABLE_BYTES)
    except FileNotFoundError:
        raise ConfigError(f"{what} {path}: not found") from None
    except OSError as e:
        raise ConfigError(f"{what} {path}: cannot be read ({e})") from None
    for enc in ("utf-8-sig", "cp1252", "latin-1"):
        try:
            text = raw.decode(enc)
            break
        except UnicodeDecodeError:
            continue
    return text.replace("\r\n", "\n").replace("\r", "\n")


_SECTION = re.compile(r"^\s*\*{3}\s*(.*?)\s*\*{3}\s*$")
_COMMA_DECIMAL = re.compile(r"^[+-]?\d+,\d+(?:[eE][+-]?\d+)?$")


def _sections(text: str) -> dict:
    """{section name (upper case; '' = the header block): [(line no, line)]}."""
    out = {"": []}
    cur = ""
    for no, line in enumerate(text.split("\n"), start=1):
        m = _SECTION.match(line)
        if m:
            cur = m.group(1).upper()
            out.setdefault(cur, [])
            continue
        if line.strip():
            out[cur].append((no, line))
    return out


def _delimiter(line: str) -> str:
    return ";" if ";" in line else ("\t" if "\t" in line else ",")


def _fields(line: str, delim: str) -> list[str]:
    return [f.strip().strip('"') for f in line.split(delim)]


def _comma_decimal_error(path: Path, no: int, text: str) -> ConfigError:
    return ConfigError(f"{path}: row {no}: {text!r} uses a comma as decimal separator; export with a point "
                       "(Windows: Region > Additional settings > Decimal symbol '.', then export again)")


def _num(path: Path, no: int, name: str, text: str) -> float:
    t = text.strip()
    if _COMMA_DECIMAL.match(t):
        raise _comma_decimal_error(path, no, t)
    return field_number(path, no, name, t)


def _key_value(line: str):
    """(key, value) of 'Key: value', 'Key,value', 'Key;value' or 'Key<TAB>value' (None if neither)."""
    for sep in (":", "\t", ";", ","):
        if sep in line:
            k, v = line.split(sep, 1)
            if k.strip() and v.strip():
                return k.strip(), v.strip().strip('"')
    return None


# ----------------------------------------------------------------------------- WFS software export


def read_export(path) -> dict:
    """One WFS software export: {"thorlabs": (K,) um, entry k-1 = Thorlabs mode k (OSA
    j + 1, piston first), "order": radial order, "header": {wavelength_nm,
    pupil_center_mm, pupil_radius_mm} where the file gives them, "reference": "user" or
    "internal" when the header says, "source": str}. ConfigError naming the file, row
    and field for a bad file (module docstring)."""
    path = Path(path)
    sec = _sections(read_text_any(path, "WFS export"))
    zname = next((k for k in sec if "ZERNIKE" in k), None)
    if zname is None:
        raise ConfigError(f"{path}: no '*** ZERNIKE FIT ***' section; in the WFS software save the measurement "
                          "with the Zernike fit included (one export file per pose)")
    rows = sec[zname]
    if not rows:
        raise ConfigError(f"{path}: section {zname}: empty; export with the Zernike fit switched on")
    hno, hline = rows[0]
    delim = _delimiter(hline)
    head = [h.lower() for h in _fields(hline, delim)]
    need = {"order": None, "frequency": None, "coefficient": None}
    for i, h in enumerate(head):
        for key in need:
            if h.startswith(key) and need[key] is None:
                need[key] = i
    if any(v is None for v in need.values()):
        raise ConfigError(f"{path}: row {hno}, section {zname} header: expected columns Index,Order,Frequency,"
                          f"Coefficient [µm], got {hline.strip()!r}")
    unit = head[need["coefficient"]]
    scale = 1e-3 if "nm" in unit else (1.0 if ("µm" in unit or "um" in unit or "[" not in unit) else None)
    if scale is None:
        raise ConfigError(f"{path}: row {hno}, field Coefficient: unit {unit!r} is not um or nm; "
                          "set the wavefront unit to um in the WFS software")
    coeff = {}
    for no, line in rows[1:]:
        f = _fields(line, delim)
        if delim == "," and len(f) > len(head) and any(_COMMA_DECIMAL.match(",".join(f[i:i + 2]))
                                                       for i in range(len(f) - 1)):
            raise _comma_decimal_error(path, no, line.strip())
        if len(f) < len(head):
            if len(f) == 1 and not f[0]:
                continue
            raise ConfigError(f"{path}: row {no}: {len(f)} fields, expected {len(head)} ({hline.strip()})")
        try:
            n = int(_num(path, no, "Order", f[need["order"]]))
            m = int(_num(path, no, "Frequency", f[need["frequency"]]))
            j = nm_to_noll(n, m)
        except ValueError:
            raise ConfigError(f"{path}: row {no}, fields Order/Frequency: ({f[need['order']]}, "
                              f"{f[need['frequency']]}) is not a Zernike mode (|m| <= n, n - |m| even)") from None
        if (n, m) in coeff:
            raise ConfigError(f"{path}: row {no}, field Order/Frequency: mode (n={n}, m={m}) appears twice")
        coeff[(n, m)] = _num(path, no, "Coefficient", f[need["coefficient"]]) * scale
    if not coeff:
        raise ConfigError(f"{path}: section {zname}: no mode rows")
    order = max(n for n, _ in coeff)
    missing = [(n, m) for n in range(1, order + 1) for m in range(-n, n + 1, 2) if (n, m) not in coeff]
    if missing:
        raise ConfigError(f"{path}: section {zname}: modes {missing[:4]} missing below the fit order {order}; "
                          "export every mode up to the fit order")
    z = np.zeros((order + 1) * (order + 2) // 2)
    for (n, m), c in coeff.items():
        z[noll_to_osa(nm_to_noll(n, m))] = c
    header = {}
    for no, line in sec[""]:
        kv = _key_value(line)
        if kv is None:
            continue
        k, v = kv[0].lower(), kv[1]
        if "wavelength" in k:
            w = _num(path, no, "Wavelength", v.split()[0])
            if "µm" in k or "um" in k or "micron" in k:
                w *= 1e3
            if not 100.0 <= w <= 20000.0:
                raise ConfigError(f"{path}: row {no}, field Wavelength: {w:g} nm is not a laser wavelength; "
                                  "give it in nm ('Wavelength [nm]')")
            header["wavelength_nm"] = w
        elif "reference pose" in k or k == "reference_pose":
            header["reference_pose"] = v.strip()
        elif k.startswith("reference"):
            header["reference"] = "user" if "user" in v.lower() else "internal"
        elif "tilt" in k and "cancel" in k:
            header["tilt_cancelled"] = v.strip().lower() in ("on", "yes", "1", "true")
    pname = next((k for k in sec if k.startswith("PUPIL")), None)
    if pname is not None:
        vals = {}
        for no, line in sec[pname]:
            kv = _key_value(line)
            if kv is None:
                continue
            k = kv[0].lower()
            axis = "x" if re.search(r"\bx\b", k) else ("y" if re.search(r"\by\b", k) else None)
            kind = "c" if ("centroid" in k or "center" in k or "centre" in k) else ("d" if "diameter" in k else None)
            if axis and kind:
                vals[kind + axis] = (no, _num(path, no, kv[0], kv[1].split()[0]))
        if "cx" in vals and "cy" in vals:
            header["pupil_center_mm"] = (vals["cx"][1], vals["cy"][1])
        if "dx" in vals and "dy" in vals:
            (no, dx), (_, dy) = vals["dx"], vals["dy"]
            if abs(dx - dy) > 2 * PUPIL_TOL_MM:
                raise ConfigError(f"{path}: row {no}, field Diameter X/Y: {dx:g} x {dy:g} mm is not a circular "
                                  "pupil; set the pupil to circular with the bench's diameter")
            header["pupil_radius_mm"] = 0.25 * (dx + dy)
    return {"thorlabs": z, "order": order, "header": header, "source": str(path)}


def export_text(zernike_thorlabs, header: dict, *, instrument: str = "WFS40-7AR", comment: str = "") -> bytes:
    """A WFS-software-layout export (the ``read_export`` layout) of one measurement, as the
    software writes it on Windows: cp1252, CRLF. zernike_thorlabs: (K,) um, entry k-1 = mode
    k (piston first); header: wavelength_nm, pupil_center_mm, pupil_radius_mm. The beam,
    Fourier and wavefront sections carry placeholders (lensforge does not read them)."""
    z = np.asarray(zernike_thorlabs, dtype=float)
    K = z.size
    order = int(round((math.sqrt(8 * K + 1) - 3) / 2))
    cx, cy = header.get("pupil_center_mm", (0.0, 0.0))
    d = 2.0 * header.get("pupil_radius_mm", 0.0)
    lines = ["Thorlabs Wavefront Sensor - measurement data", f"Instrument: {instrument}",
             f"Wavelength [nm]: {header['wavelength_nm']:.3f}", "Pupil: circular",
             f"Zernike fit up to order: {order}", "Cancel wavefront tilt: off", "Reference: internal"]
    if comment:
        lines.append(f"Comment: {comment}")
    lines += ["", "*** PUPIL ***", f"Centroid X [mm],{cx:.6f}", f"Centroid Y [mm],{cy:.6f}",
              f"Diameter X [mm],{d:.6f}", f"Diameter Y [mm],{d:.6f}", "",
              "*** BEAM ***", "Centroid X [mm],0.000", "Centroid Y [mm],0.000", "", "*** ZERNIKE FIT ***",
              "Index,Order,Frequency,Coefficient [µm]"]
    k = 0
    for n in range(order + 1):
        for m in range(-n, n + 1, 2):  # OSA/ANSI sequence: Thorlabs index k = OSA j + 1
            lines.append(f"{k + 1},{n},{m},{float(z[k])!r}")
            k += 1
    lines += ["", "*** FOURIER / OPTOMETRIC ***", "Sphere [dpt],0.000", "", "*** WAVEFRONT ***",
              "y / x [mm],0.000", "0.000,", ""]
    return "\r\n".join(lines).encode("cp1252")


def pose_id_from_name(path, pattern: str | None = None) -> str:
    """Pose id of a measurement file: the last integer in its name (``pose_07.csv`` -> "7"),
    or the first group of ``pattern`` (a regular expression searched in the file name)."""
    name = Path(path).name
    pat = pattern or POSE_ID_PATTERN
    try:
        m = re.search(pat, name)
    except re.error as e:
        raise ConfigError(f"--pose-pattern: {pat!r} is not a regular expression ({e})") from None
    if m is None:
        raise ConfigError(f"{path}: no pose id in the file name (pattern {pat!r}); name the files by pose "
                          "(pose_07.csv) or give --pose-pattern")
    g = m.group(1) if m.groups() else m.group(0)
    g = g.strip()
    return str(int(g)) if re.fullmatch(r"[+-]?\d+", g) else g


def expand_measurements(spec, suffixes=(".csv", ".txt", ".npz")) -> list[Path]:
    """The files of a folder (with these suffixes) or of a glob pattern, sorted; [] if ``spec``
    is neither (a plain file)."""
    p = Path(spec)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in suffixes
                       and not f.name.startswith("."))
        if not files:
            raise ConfigError(f"{p}: no measurement files ({', '.join(suffixes)}) in the folder")
        return files
    if any(c in str(spec) for c in "*?["):
        files = sorted(Path(f) for f in _glob.glob(str(spec)) if Path(f).is_file())
        if not files:
            raise ConfigError(f"{spec}: the pattern matches no file")
        return files
    return []


def _ids_of(files, pattern):
    ids = [pose_id_from_name(f, pattern) for f in files]
    seen = {}
    for i, f in zip(ids, files):
        if i in seen:
            raise ConfigError(f"{f}: pose id {i} also in {seen[i].name}; one file per pose (or --pose-pattern)")
        seen[i] = f
    return ids


def read_export_folder(spec, pattern: str | None = None) -> dict:
    """The fields of a ``formats.WfsData`` (ids, zernike (n, K) Thorlabs order, order, header,
    source, rows) of a folder or glob of WFS exports, one per pose, the pose id from each
    file name (``pose_id_from_name``). Every file must share the fit order, wavelength and
    pupil; the tilt check (``check_tilt_not_cancelled``) runs. ``formats.read_wfs`` (format
    ``thorlabs_export``) returns it as WfsData."""
    files = expand_measurements(spec, (".csv", ".txt")) or [Path(spec)]  # or one export file
    ids = _ids_of(files, pattern)
    recs = [read_export(f) for f in files]
    order = min(r["order"] for r in recs)
    K = (order + 1) * (order + 2) // 2
    h0 = recs[0]["header"]
    for r in recs[1:]:
        for key in ("wavelength_nm", "pupil_radius_mm"):
            if key in h0 and key in r["header"] and abs(r["header"][key] - h0[key]) > 1e-9:
                raise ConfigError(f"{r['source']}: field {key}: {r['header'][key]:g} differs from "
                                  f"{h0[key]:g} in {recs[0]['source']}; record every pose with the same settings")
    z = np.array([r["thorlabs"][:K] for r in recs])
    header = {k: v for k, v in h0.items() if k in ("wavelength_nm", "pupil_center_mm", "pupil_radius_mm")}
    header["instrument_file"] = "thorlabs_export"
    header["times"] = {i: f.stat().st_mtime for i, f in zip(ids, files)}  # for a time-stamped robot log
    refs = {r["header"].get("reference_pose") for r in recs} - {None}
    if refs:
        header["reference_pose"] = sorted(refs)[0]
    if any(r["header"].get("reference") == "user" for r in recs):
        header["reference"] = "user"
    check_not_all_zero(z, str(spec))  # a file of zeros is named as such, before the tilt check
    check_tilt_not_cancelled(z[:, 1:3], str(spec), "Zernike tilt modes (Thorlabs 2, 3)",
                             any(r["header"].get("tilt_cancelled") for r in recs))
    return {"ids": tuple(ids), "zernike": z, "order": order, "header": header, "source": str(spec),
            "rows": tuple(range(1, len(ids) + 1))}


def check_not_all_zero(zernike_thorlabs, source: str) -> None:
    """ConfigError for a WFS file whose every coefficient (piston aside) is 0; the readers
    run it before the tilt check, whose advice would be wrong for a file of zeros."""
    z = np.asarray(zernike_thorlabs, float)
    if np.all((z[:, 1:] if z.shape[1] > 1 else z) == 0.0):
        raise ConfigError(f"{source}: every coefficient is 0: no sensor measures a perfect plane wave; export the "
                          "WFS software's Zernike table while the sensor runs")


def check_tilt_not_cancelled(tilt, source: str, what: str, flagged: bool = False, zero: float = TILT_ZERO_UM) -> None:
    """ConfigError when the tilt values (n, 2) are zero in every pose (or the file says
    tilt cancel is on): the wavefront tilt, which carries the lens's decentre, was removed."""
    tilt = np.asarray(tilt, dtype=float)
    if flagged or (tilt.size and np.all(np.abs(tilt) <= zero)):
        raise ConfigError(f"{source}: {what} are zero in every pose: the measurements were taken with tilt "
                          "cancel ON; switch it OFF (WFS software: Setup > cancel wavefront tilt off; SDK: "
                          "WFS_CalcSpotToReferenceDeviations(instr, cancelWavefrontTilt=0)) and record again")


# ----------------------------------------------------------------------------- SDK spot fields


@dataclass(frozen=True, eq=False)
class SpotFields:
    """Spot-deviation fields by pose id (``read_spot_fields``).

    ids (n,); slopes: (n, ny, nx, 2) rad (x, y), NaN where no spot; centres: (ny, nx, 2)
    lenslet centres in {S} (mm); focal_length_um, lenslet_pitch_um, pixel_pitch_um: the
    MLA data; header: wavelength_nm, pupil_center_mm, pupil_radius_mm where given,
    reference_pose (user reference) if any; source; files."""

    ids: tuple
    slopes: np.ndarray
    centres: np.ndarray
    focal_length_um: float
    lenslet_pitch_um: float
    pixel_pitch_um: float
    header: dict = field(default_factory=dict)
    source: str = ""
    files: tuple = ()


_SPOT_SCALARS = ("focal_length_um", "lenslet_pitch_um", "pixel_pitch_um")
_SPOT_OPTIONAL = ("wavelength_nm", "pupil_radius_mm")


def _spot_csv(path: Path) -> dict:
    text = read_text_any(path, "spot field")
    meta, header, rows = {}, None, []
    for no, line in enumerate(text.split("\n"), start=1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            kv = s.lstrip("#").strip()
            if ":" in kv:
                k, v = kv.split(":", 1)
                meta[k.strip().lower()] = (no, v.strip())
            continue
        if header is None:
            header = (no, [h.lower() for h in _fields(s, _delimiter(s))])
            if header[1][:4] != ["iy", "ix", "dx_px", "dy_px"]:
                raise ConfigError(f"{path}: row {no}, header: expected iy,ix,dx_px,dy_px, got {s!r}")
            delim = _delimiter(s)
            continue
        f = _fields(s, delim)
        if len(f) != 4:
            if delim == "," and len(f) > 4:
                raise _comma_decimal_error(path, no, s)
            raise ConfigError(f"{path}: row {no}: {len(f)} fields, expected 4 (iy,ix,dx_px,dy_px)")
        iy, ix = (int(_num(path, no, n, t)) for n, t in zip(("iy", "ix"), f[:2]))
        d = [float("nan") if t.lower() in ("", "nan") else _num(path, no, n, t) for n, t in zip(("dx_px", "dy_px"), f[2:])]
        rows.append((no, iy, ix, d))
    if header is None or not rows:
        raise ConfigError(f"{path}: no lenslet rows; expected a header iy,ix,dx_px,dy_px and one row per lenslet")
    out = {}
    for key in _SPOT_SCALARS + _SPOT_OPTIONAL:
        if key in meta:
            out[key] = _num(path, meta[key][0], key, meta[key][1])
    for key in ("center_offset_mm", "pupil_center_mm"):
        if key in meta:
            no, v = meta[key]
            vals = [_num(path, no, key, t) for t in re.split(r"[;,\s]+", v) if t]
            if len(vals) != 2:
                raise ConfigError(f"{path}: row {no}, field {key}: expected two numbers x, y")
            out[key] = tuple(vals)
    for key in ("reference_pose", "tilt_cancelled"):
        if key in meta:
            out[key] = meta[key][1]
    ny = max(r[1] for r in rows) + 1
    nx = max(r[2] for r in rows) + 1
    dx = np.full((ny, nx), np.nan)
    dy = np.full((ny, nx), np.nan)
    for no, iy, ix, d in rows:
        if iy < 0 or ix < 0:
            raise ConfigError(f"{path}: row {no}, field iy/ix: negative lenslet index")
        dx[iy, ix], dy[iy, ix] = d
    out["deviation_x_px"], out["deviation_y_px"] = dx, dy
    return out


def _spot_npz(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: not a readable NPZ spot field ({e})") from None
    out = {}
    for key, v in data.items():
        if key in ("reference_pose", "tilt_cancelled"):
            out[key] = str(v)
        elif key in ("deviation_x_px", "deviation_y_px"):
            out[key] = np.asarray(v, dtype=float)
        else:
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                continue  # unknown non-numeric entries are not data we read
            out[key] = float(a) if a.ndim == 0 else tuple(a.ravel().tolist())
    return out


def read_spot_field(path) -> dict:
    """One spot field (CSV or NPZ, module docstring), validated: {"slopes": (ny, nx, 2) rad,
    "centres": (ny, nx, 2) mm, the MLA data, "header": {...}, "source"}."""
    path = Path(path)
    d = _spot_npz(path) if path.suffix.lower() == ".npz" else _spot_csv(path)
    for key in _SPOT_SCALARS + ("center_offset_mm",):
        if key not in d:
            raise ConfigError(f"{path}: field {key}: missing; save the MLA data of WFS_GetMlaData with the field "
                              "(focal_length_um, lenslet_pitch_um, pixel_pitch_um, center_offset_mm)")
    for key in _SPOT_SCALARS:
        if not (isinstance(d[key], float) and d[key] > 0):
            raise ConfigError(f"{path}: field {key}: must be one positive number, got {d[key]!r}")
    if len(d["center_offset_mm"]) != 2:
        raise ConfigError(f"{path}: field center_offset_mm: expected (x, y) in mm")
    for key in ("deviation_x_px", "deviation_y_px"):
        if key not in d or np.ndim(d[key]) != 2:
            raise ConfigError(f"{path}: field {key}: missing or not a [Y][X] array (WFS_GetSpotDeviations)")
    dx, dy = d["deviation_x_px"], d["deviation_y_px"]
    if dx.shape != dy.shape:
        raise ConfigError(f"{path}: fields deviation_x_px/deviation_y_px: shapes {dx.shape} and {dy.shape} differ")
    if np.any(np.isinf(dx)) or np.any(np.isinf(dy)):
        raise ConfigError(f"{path}: field deviation: infinite value; undetected spots are NaN")
    ny, nx = dx.shape
    pitch = d["lenslet_pitch_um"] * 1e-3
    cx, cy = d["center_offset_mm"]
    X, Y = np.meshgrid(pitch * (np.arange(nx) - 0.5 * (nx - 1)) + cx, pitch * (np.arange(ny) - 0.5 * (ny - 1)) + cy)
    k = d["pixel_pitch_um"] / d["focal_length_um"]  # rad per pixel of deviation
    header = {key: d[key] for key in ("wavelength_nm", "pupil_radius_mm", "pupil_center_mm") if key in d}
    if "reference_pose" in d and str(d["reference_pose"]).strip():
        header["reference_pose"] = str(d["reference_pose"]).strip()
    if str(d.get("tilt_cancelled", "")).strip().lower() in ("1", "on", "true", "yes"):
        header["tilt_cancelled"] = True
    return {"slopes": np.stack([dx * k, dy * k], axis=-1), "centres": np.stack([X, Y], axis=-1),
            "focal_length_um": d["focal_length_um"], "lenslet_pitch_um": d["lenslet_pitch_um"],
            "pixel_pitch_um": d["pixel_pitch_um"], "header": header, "source": str(path)}


def read_spot_fields(spec, pattern: str | None = None) -> SpotFields:
    """SpotFields of a folder or glob of spot-field files (CSV/NPZ), one per pose, ids from
    the file names. Every file must share the grid and MLA data; the tilt check runs
    (the mean spot deviation is zero in every pose when tilt cancel was on)."""
    files = expand_measurements(spec, (".csv", ".npz"))
    if not files:
        files = [Path(spec)]
    ids = _ids_of(files, pattern)
    recs = [read_spot_field(f) for f in files]
    r0 = recs[0]
    for r in recs[1:]:
        if r["slopes"].shape != r0["slopes"].shape or not np.allclose(r["centres"], r0["centres"], atol=1e-9):
            raise ConfigError(f"{r['source']}: lenslet grid differs from {r0['source']}; every pose must come from "
                              "the same sensor and MLA settings")
        for key in _SPOT_SCALARS:
            if abs(r[key] - r0[key]) > 1e-9 * r0[key]:
                raise ConfigError(f"{r['source']}: field {key}: {r[key]:g} differs from {r0[key]:g} in "
                                  f"{r0['source']}")
    slopes = np.array([r["slopes"] for r in recs])
    header = dict(r0["header"])
    header["instrument_file"] = "spot_field"
    header["times"] = {i: f.stat().st_mtime for i, f in zip(ids, files)}
    for r in recs:
        if "reference_pose" in r["header"]:
            header["reference_pose"] = r["header"]["reference_pose"]
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(slopes.reshape(len(recs), -1, 2), axis=1) / (r0["pixel_pitch_um"] / r0["focal_length_um"])
    check_tilt_not_cancelled(mean, str(spec), "the mean spot deviations (x, y)",
                             any(r["header"].get("tilt_cancelled") for r in recs), TILT_ZERO_PX)
    return SpotFields(tuple(ids), slopes, r0["centres"], r0["focal_length_um"], r0["lenslet_pitch_um"],
                      r0["pixel_pitch_um"], header, str(spec), tuple(str(f) for f in files))


def _grid_deviations(slopes_px) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(slopes_px, dtype=float)
    return d[..., 0], d[..., 1]


def spot_field_npz(deviation_px, *, focal_length_um: float, lenslet_pitch_um: float, pixel_pitch_um: float,
                   center_offset_mm=(0.0, 0.0), header: dict | None = None) -> bytes:
    """NPZ bytes of one spot field: deviation_px (ny, nx, 2) pixels ([Y][X], NaN = no spot)."""
    import io

    dx, dy = _grid_deviations(deviation_px)
    extra = {}
    for k, v in (header or {}).items():
        extra[k] = np.asarray(str(v)) if k == "reference_pose" else np.asarray(v, dtype=float)
    buf = io.BytesIO()
    np.savez(buf, deviation_x_px=dx, deviation_y_px=dy, focal_length_um=np.float64(focal_length_um),
             lenslet_pitch_um=np.float64(lenslet_pitch_um), pixel_pitch_um=np.float64(pixel_pitch_um),
             center_offset_mm=np.asarray(center_offset_mm, float), **extra)
    return buf.getvalue()


def spot_field_csv(deviation_px, *, focal_length_um: float, lenslet_pitch_um: float, pixel_pitch_um: float,
                   center_offset_mm=(0.0, 0.0), header: dict | None = None, only_finite: bool = True) -> str:
    """CSV text of one spot field (the ``read_spot_field`` CSV layout); only_finite: leave
    out lenslets with no spot (the reader sets them NaN)."""
    dx, dy = _grid_deviations(deviation_px)
    lines = ["# lensforge spot field: WFS_GetSpotDeviations (px, [Y][X]) + WFS_GetMlaData",
             f"# focal_length_um: {focal_length_um!r}", f"# lenslet_pitch_um: {lenslet_pitch_um!r}",
             f"# pixel_pitch_um: {pixel_pitch_um!r}",
             f"# center_offset_mm: {float(center_offset_mm[0])!r}, {float(center_offset_mm[1])!r}"]
    for k, v in (header or {}).items():
        lines.append(f"# {k}: " + (str(v) if k == "reference_pose" else ", ".join(repr(float(a)) for a in np.atleast_1d(v))))
    lines.append("iy,ix,dx_px,dy_px")
    ny, nx = dx.shape
    for iy in range(ny):
        for ix in range(nx):
            if only_finite and not (np.isfinite(dx[iy, ix]) and np.isfinite(dy[iy, ix])):
                continue
            lines.append(f"{iy},{ix},{float(dx[iy, ix])!r},{float(dy[iy, ix])!r}")
    # the grid's extent must survive even when its far corner has no spot
    if only_finite and not (np.isfinite(dx[-1, -1]) and np.isfinite(dy[-1, -1])):
        lines.append(f"{ny - 1},{nx - 1},nan,nan")
    return "\n".join(lines) + "\n"
