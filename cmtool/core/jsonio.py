"""File reading/writing with user-facing errors and atomic writes (shared by all file formats)."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import secrets
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from cmtool.core.errors import CmtoolError
from cmtool.core.outputs import os_reason, target


def read_text(path: str | os.PathLike) -> str:
    """A UTF-8 text file's contents; a missing, unreadable or non-UTF-8 file becomes a :class:`CmtoolError`."""
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such file")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise CmtoolError(f"{path}: not a UTF-8 text file (byte {e.start} is {e.object[e.start]:#04x})") from None
    except OSError as e:
        raise CmtoolError(f"{path}: cannot read it: {os_reason(e)}") from None


MAX_DEPTH = 64  # of nested JSON arrays and objects (cmtool's own files nest 5 deep)


def loads(text: str, where: str):
    """The JSON value of ``text`` (the one JSON parser of cmtool's readers); malformed JSON, or JSON nested deeper
    than ``MAX_DEPTH``, is a :class:`CmtoolError` naming ``where``."""
    depth = nesting(text)
    if depth > MAX_DEPTH:
        raise CmtoolError(f"{where}: JSON nested {depth} levels deep (cmtool reads at most {MAX_DEPTH})")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise MalformedJson(f"{where}: malformed JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None


class MalformedJson(CmtoolError):
    """Text that is not JSON."""


_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
_STEP = np.zeros(256, np.int32)  # +1 for each opening bracket, -1 for each closing one
_STEP[[ord("["), ord("{")]], _STEP[[ord("]"), ord("}")]] = 1, -1


def nesting(text: str, chunk: int = 1 << 22) -> int:
    """How deep the arrays and objects of JSON ``text`` nest (brackets inside strings not counted), in one
    vectorised pass of bounded memory."""
    if "\\" in text:
        text = _STRING.sub('""', text)
    data = np.frombuffer(text.encode("utf-8"), np.uint8)
    depth = deepest = 0
    inside = False
    for start in range(0, len(data), chunk):
        b = data[start:start + chunk]
        quote = b == ord('"')
        step = _STEP[b]
        if inside or quote.any():  # brackets in strings do not count (a quote opens or closes one; no escaped ones)
            step[((np.cumsum(quote, dtype=np.int32) + inside) % 2 == 1) | quote] = 0
        levels = depth + np.cumsum(step, dtype=np.int32)
        if len(levels):
            deepest, depth = max(deepest, int(levels.max())), int(levels[-1])
        inside = bool((inside + int(quote.sum())) % 2)
    return deepest


def read_json(path: str | os.PathLike, limit: int | None = None):
    """Load a JSON file; a missing file, non-UTF-8 text, malformed or too deeply nested JSON, or a file of over
    ``limit`` bytes (refused unread) becomes a :class:`CmtoolError`."""
    if limit is not None and Path(path).is_file() and (size := os.stat(path).st_size) > limit:
        raise CmtoolError(f"{path}: a file of {size:,} bytes; cmtool reads such a file up to {limit:,} bytes "
                          f"({limit / 2**20:g} MiB)")
    return loads(read_text(path), str(path))


class MalformedLine(CmtoolError):
    """A line of a JSON Lines file that is not JSON (``lineno`` counts from 1)."""

    def __init__(self, message: str, lineno: int):
        super().__init__(message)
        self.lineno = lineno


def json_lines(path: str | os.PathLike) -> list[tuple[int, object]]:
    """(line number, value) of each non-empty line of a UTF-8 JSON Lines file; a malformed line is a
    :class:`MalformedLine` naming the file and the line."""
    out = []
    for lineno, line in enumerate(read_text(path).splitlines(), start=1):
        if line.strip():
            try:
                out.append((lineno, loads(line, f"{path}: line {lineno}")))
            except MalformedJson as e:
                raise MalformedLine(str(e), lineno) from None
    return out


@contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w"):
    """Open a temporary file beside ``path`` for writing; when the block succeeds it is renamed over
    ``path``, when it fails it is removed. So a crash never leaves a half-written file behind. An OS error
    (a file in the way, no permission, a full disk) becomes a :class:`CmtoolError` naming ``path``; a path that must
    not be written (:func:`cmtool.core.outputs.target`) is refused."""
    path = target(path)
    tmp = temporary(path)  # named before it exists: a signal at any point below leaves nothing behind
    try:
        with os.fdopen(_create(tmp), mode, encoding=None if "b" in mode else "utf-8") as f:
            yield f
        os.replace(tmp, path)
    except OSError as e:
        _remove(tmp)
        raise CmtoolError(f"cannot write {path}: {os_reason(e)}") from None
    except BaseException:
        _remove(tmp)
        raise


class OutputSet:
    """Files a command writes as one set: each goes to a temporary file beside its destination, :meth:`commit`
    renames them all into place when the command has succeeded, and :meth:`discard` (it failed) removes the
    temporaries, so the files of an earlier run stay as they were."""

    def __init__(self):
        self.staged: list[tuple[str, Path]] = []

    def write_bytes(self, path: str | os.PathLike, data: bytes) -> None:
        path = target(path)
        tmp = temporary(path)
        self.staged.append((tmp, path))
        try:
            with os.fdopen(_create(tmp), "wb") as f:
                f.write(data)
        except OSError as e:
            raise CmtoolError(f"cannot write {path}: {os_reason(e)}") from None

    def write_text(self, path: str | os.PathLike, text: str) -> None:
        self.write_bytes(path, text.encode("utf-8"))

    def commit(self) -> None:
        """Rename every staged file into place."""
        for tmp, path in self.staged:
            try:
                os.replace(tmp, path)
            except OSError as e:
                raise CmtoolError(f"cannot write {path}: {os_reason(e)}") from None
        self.staged = []

    def discard(self) -> None:
        for tmp, _ in self.staged:
            _remove(tmp)
        self.staged = []


def temporary(path: Path, stable: bool = False) -> str:
    """A name for a temporary file beside ``path``: hidden, ending in .tmp, and of one length whatever the length of
    ``path``'s own name (the temporary of a legal name is legal too); random (a new file), or with ``stable`` the same
    for the same ``path`` (a file that a later step finds again)."""
    tag = hashlib.sha256(path.name.encode()).hexdigest()[:12] if stable else secrets.token_hex(6)
    return str(path.parent / f".cmtool-{tag}.tmp")


def _create(tmp: str) -> int:
    """Create the file ``tmp`` (and its folder), new, with the permissions ``open`` gives under the umask."""
    Path(tmp).parent.mkdir(parents=True, exist_ok=True)
    return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)


def _remove(tmp: str | None) -> None:
    if tmp is not None and os.path.exists(tmp):
        os.unlink(tmp)


def file_mode() -> int:
    """The permissions a new file gets from ``open`` under the process's umask (0644 under the usual 022)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_open(path) as f:
        f.write(text)


def json_text(obj) -> str:
    """``obj`` as one line of compact, strict JSON: NaN and infinite numbers (which JSON has no words for, and
    readers other than Python's refuse) are written as null."""
    try:  # walking every number to replace the non-finite ones only when there is one
        return json.dumps(obj, separators=(",", ":"), allow_nan=False) + "\n"
    except ValueError:
        return json.dumps(strict(obj), separators=(",", ":"), allow_nan=False) + "\n"


def strict(obj):
    """``obj`` with every non-finite float (NaN, infinities) replaced by None, in nested dicts, lists and tuples."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    return obj


def write_json(path: str | os.PathLike, obj) -> None:
    write_text_atomic(path, json_text(obj))


class JsonFile:
    """``save`` and ``load`` for a type with ``to_json()`` and ``from_json(obj, where=...)`` (one object a file)."""

    def save(self, path) -> None:
        write_json(path, self.to_json())

    @classmethod
    def load(cls, path):
        return cls.from_json(read_json(path), where=str(path))


class Fields:
    """Typed access to a JSON object that names the offending field in its errors.

    ``where`` names the file (and line), ``path`` the object inside it; errors read
    ``"map.json: lanes[3].width: expected a number, got 'wide'"``.
    """

    def __init__(self, obj, where: str, path: str = ""):
        if not isinstance(obj, dict):
            raise CmtoolError(f"{where}: {path or 'top level'}: expected a JSON object, got {type(obj).__name__}")
        self.obj, self.where, self.path = obj, where, path

    def at(self, key: str) -> str:
        """The path of ``key`` inside this object, e.g. ``lanes[3].width``."""
        return f"{self.path}.{key}" if self.path else key

    def fail(self, key: str, msg: str):
        raise CmtoolError(f"{self.where}: {self.at(key)}: {msg}")

    def get(self, key: str, types, default=..., allow_none: bool = False):
        if key not in self.obj:
            if default is ...:
                self.fail(key, "missing")
            return default
        value = self.obj[key]
        if value is None and allow_none:
            return None
        if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
            self.fail(key, f"expected {_type_name(types)}, got {value!r}")
        if not isinstance(value, types):
            self.fail(key, f"expected {_type_name(types)}, got {_short(value)}")
        if isinstance(value, float) and not (value == value and abs(value) != float("inf")):
            self.fail(key, "NaN or infinite number")
        if isinstance(value, int) and abs(value) > 2**63:
            self.fail(key, f"number too large ({len(str(abs(value)))} digits)")
        return value

    def header(self, fmt: str | None, kind: str, version: int = 1) -> None:
        """Check a file's ``format`` tag (when ``fmt`` is given) and its ``version``."""
        if fmt is not None and self.get("format", str) != fmt:
            self.fail("format", f"expected {fmt!r} (is this {kind}?)")
        if self.get("version", int) != version:
            self.fail("version", f"unsupported version (this cmtool reads version {version})")

    def number(self, key: str, default=...) -> float:
        return float(self.get(key, (int, float), default))

    def points(self, key: str, min_points: int = 2):
        """A list of [x, y] pairs as a float64 (N, 2) array."""
        from cmtool.core.geometry import as_polyline

        value = self.get(key, list)
        try:
            return as_polyline(value, min_points=min_points)
        except (ValueError, TypeError) as e:
            self.fail(key, str(e))

    def lines(self, key: str, default=...) -> list:
        """A list of polylines, each a float64 (N, 2) array with N >= 2."""
        from cmtool.core.geometry import as_polyline

        out = []
        for k, pts in enumerate(self.get(key, list, default)):
            try:
                out.append(as_polyline(pts))
            except (ValueError, TypeError) as e:
                self.fail(f"{key}[{k}]", str(e))
        return out


def _type_name(types) -> str:
    names = {int: "an integer", float: "a number", str: "a string", list: "a list", dict: "an object", bool: "true/false"}
    types = types if isinstance(types, tuple) else (types,)
    if set(types) == {int, float}:
        return "a number"
    return " or ".join(names.get(t, t.__name__) for t in types)


def _short(value) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."
