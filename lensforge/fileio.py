"""File I/O shared by every layer: atomic writes and JSON/TOML reads with one clear error.

Sits beside ``errors.py`` at the bottom of the import graph (imports nothing of lensforge
but the errors and ``interrupts.committing``), so optics, design, manufacturing, verification and the CLI all use it.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import tomllib
from contextlib import contextmanager
from pathlib import Path

from .errors import ConfigError
from .interrupts import committing, note_staging

__all__ = ["write_atomic", "read_json", "read_toml", "json_default", "dumps_json", "check_output", "staged_dir",
           "Staged", "MAX_INPUT_BYTES", "MAX_TABLE_BYTES", "read_bounded", "public_path", "public_text"]


_TEMP_NAME = re.compile(r"^\.(.+?)\.(?:[A-Za-z0-9_]{8}\.tmp|old-\d+)$")


def public_path(path) -> str:
    """``path`` as a user should read it: the hidden temporary names of :func:`write_atomic`,
    :func:`staged_dir` and ``formats.write_bundle`` (``.NAME.xxxxxxxx.tmp``, ``.NAME.old-PID``)
    replaced by the final NAME, so that no message names an internal temp path."""
    parts = Path(str(path)).parts
    return str(Path(*[(m.group(1) if (m := _TEMP_NAME.match(q)) else q) for q in parts])) if parts else str(path)


_TEMP_IN_TEXT = re.compile(r"(^|[/\s'\"(])\.([^/\s'\"]+?)\.(?:[A-Za-z0-9_]{8}\.tmp|old-\d+)(?=$|[/\s'\":),])")


def public_text(text: str) -> str:
    """A message with every hidden temporary path component replaced by its final name
    (see :func:`public_path`)."""
    return _TEMP_IN_TEXT.sub(lambda m: m.group(1) + m.group(2), text)


def write_atomic(path, data: bytes | str) -> Path:
    """Write a file atomically: temp file in the same folder, fsync, rename.

    The file gets the permissions the umask gives a new file (mkstemp's are 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    note_staging(tmp)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _parse(path, what: str, fmt: str, loads, errors):
    p = Path(path)
    text = _read_text(p, what)
    try:
        return loads(text)
    except errors as e:
        detail = f"{e.msg} at line {e.lineno}" if isinstance(e, json.JSONDecodeError) else str(e)
        raise ConfigError(f"{what} {p}: not valid {fmt} ({detail})") from None
    except RecursionError:
        raise ConfigError(f"{what} {p}: nested too deeply to be a lensforge file") from None


def read_json(path, what: str):
    """Parsed JSON of ``path``; ConfigError naming ``what`` (e.g. "design file") otherwise."""
    return _parse(path, what, "JSON", json.loads, json.JSONDecodeError)


def read_toml(path, what: str) -> dict:
    """Parsed TOML of ``path``; ConfigError naming ``what`` (e.g. "bench file") otherwise."""
    return _parse(path, what, "TOML", tomllib.loads, tomllib.TOMLDecodeError)


# Input files are small; a bigger one is not a lensforge file (and would only fill memory).
MAX_INPUT_BYTES = 256 * 2**20
# A CSV table of poses or Zernike rows: 2000 rows of 66 modes are ~2 MB; 32 MiB is far beyond any session.
MAX_TABLE_BYTES = 32 * 2**20


def read_bounded(path, what: str, limit: int | None = None) -> bytes:
    """The bytes of an input file, at most ``limit`` (default ``MAX_INPUT_BYTES``): a bigger
    file -- or a device that never ends, /dev/zero, /dev/urandom, a FIFO -- is refused after
    reading limit + 1 bytes, never read whole. ConfigError for a folder or an oversized input;
    OSError (not found, permission) is the caller's to word."""
    p = Path(path)
    limit = MAX_INPUT_BYTES if limit is None else int(limit)
    if p.is_dir():
        raise ConfigError(f"{what} {p}: is a folder; give a file")
    st = p.stat()
    if st.st_size > limit:
        raise ConfigError(f"{what} {p}: {st.st_size / 2**20:.0f} MiB is too large for a "
                          f"lensforge input file (limit {limit / 2**20:.0f} MiB)")
    with open(p, "rb") as fh:
        data = fh.read(limit + 1)
    if len(data) > limit:
        kind = "a regular file" if os.path.isfile(p) else "a device or pipe that does not end"
        raise ConfigError(f"{what} {p}: more than {limit / 2**20:.0f} MiB ({kind}); a lensforge input file is "
                          "smaller: give the file itself")
    return data


def _read_text(p: Path, what: str) -> str:
    """UTF-8 text of an input file; a leading byte-order mark (Windows editors) is dropped."""
    try:
        data = read_bounded(p, what)
    except FileNotFoundError:
        raise ConfigError(f"{what} {p}: not found") from None
    except OSError as e:
        raise ConfigError(f"{what} {p}: cannot be read ({e.strerror or e})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{what} {p}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None


def json_default(o):
    """``json.dumps`` default for numpy arrays and scalars and paths."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj) -> str:
    """Strict (no NaN) indented JSON with numpy support."""
    return json.dumps(obj, indent=2, allow_nan=False, default=json_default)


# --- output targets: checked before work starts, written all or nothing ----------------


def check_output(path, *, folder: bool, need_mb: float = 1.0, option: str = "-o/--out") -> Path:
    """Check an output target before any work starts; returns it as a Path.

    folder: the target is a folder (files go inside it) rather than one file. Refused
    with a ConfigError naming ``option``: a file target that is an existing folder, a
    folder target that is a file, a path under a file, a folder that cannot be
    written (read-only, no permission), less than ``need_mb`` MiB free.
    """
    import shutil

    p = Path(path)
    if folder and p.exists() and not p.is_dir():
        raise ConfigError(f"{option} {p}: is a file, not a folder; choose a folder")
    if not folder and p.is_dir():
        raise ConfigError(f"{option} {p}: is a folder; give a file name, e.g. {p / 'out.json'}")
    anc = p if (folder and p.is_dir()) else p.parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise ConfigError(f"{option} {p}: {anc} is a file, so nothing can be created under it; choose another path")
    try:
        fd, probe = tempfile.mkstemp(dir=anc, prefix=".lensforge-probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ConfigError(f"{option} {p}: cannot write in {anc} ({e.strerror or e}); choose a writable folder") from None
    free = shutil.disk_usage(anc).free
    if free < need_mb * 2**20:
        raise ConfigError(f"{option} {p}: only {free / 2**20:.2f} MiB free in {anc}, about {need_mb:g} MiB needed; "
                          "free space or choose another folder")
    return p


class Staged:
    """A temporary folder beside an output folder; see :func:`staged_dir`."""

    def __init__(self, tmp: Path, out: Path):
        self.tmp, self.out = tmp, out

    def final(self, p) -> Path:
        """Where a file written into the temporary folder will end up."""
        return self.out / Path(p).relative_to(self.tmp)

    def relocate(self, text: str) -> str:
        """Text (JSON, a summary) with temporary paths replaced by the final ones."""
        return text.replace(str(self.tmp), str(self.out))


@contextmanager
def staged_dir(out):
    """Outputs all or nothing: yields a :class:`Staged` whose ``tmp`` folder (beside ``out``,
    same file system) receives the files; on success they move into ``out`` (created if
    needed; a missing ``out`` is one rename), on any error or interrupt they are deleted.
    """
    import shutil

    out = Path(out)
    if not out.name:  # ".", "..": the temporary folder needs the output folder's own name
        out = out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp"))
    note_staging(tmp)
    try:
        yield Staged(tmp, out)
        _fsync_tree(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)
        with committing():  # all in place or nothing, whatever signal arrives meanwhile
            if not out.exists():
                os.rename(tmp, out)
            else:
                _merge(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _fsync_tree(root: Path) -> None:
    for f in root.rglob("*"):
        if f.is_file():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())


def _merge(src: Path, dst: Path) -> None:
    """Move src's entries into the existing folder dst (renames; files replace files)."""
    for f in sorted(src.iterdir()):
        target = dst / f.name
        if f.is_dir() and target.is_dir():
            _merge(f, target)
        else:
            if target.is_dir():
                raise ConfigError(f"-o/--out {dst}: {target} is a folder where a file should go; move it away")
            os.replace(f, target)
