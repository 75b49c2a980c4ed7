"""TOML tables as dataclasses: every key checked against the dataclass's fields and type hints, so a wrong
key or type is a one-line error naming the file and the key (recipes, checkpoint configs)."""

from __future__ import annotations

import dataclasses
import math
import sys
import types
import typing
from pathlib import Path

from cmtool.core.errors import CmtoolError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def read_toml(path: Path, what: str = "TOML") -> dict:
    """The table of a TOML file; a missing, undecodable or malformed file is a one-line error."""
    path = Path(path)
    if not path.is_file():
        raise CmtoolError(f"{path}: no such {what} file")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise CmtoolError(f"{path}: malformed TOML: {e}") from None
    except UnicodeDecodeError:
        raise CmtoolError(f"{path}: not a UTF-8 text file") from None
    except RecursionError:
        raise CmtoolError(f"{path}: TOML nested too deeply to read") from None


def toml_fields(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.metadata.get("toml", True)]


def from_table(cls, table, where: str, prefix: str = ""):
    """Construct dataclass ``cls`` from a TOML table, checking keys and types."""
    if not isinstance(table, dict):
        raise CmtoolError(f"{where}{prefix.rstrip('.') or 'recipe'}: expected a table")
    fields = {f.name: f for f in toml_fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise CmtoolError(f"{where}{prefix}{unknown[0]}: unknown key (known: {', '.join(fields)})")
    missing = [n for n, f in fields.items() if n not in table and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise CmtoolError(f"{where}{prefix}{missing[0]}: missing")
    return cls(**{k: _convert(hints[k], v, where, prefix + k) for k, v in table.items()})


def _convert(tp, value, where: str, key: str):
    """Check ``value`` against type hint ``tp`` (int/float/str/bool, lists, tuples, Optional, dataclasses)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:  # TOML has no null; kept for completeness
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _convert(inner, value, where, key)
    if dataclasses.is_dataclass(tp):
        return from_table(tp, value, where, key + ".")
    if origin in (list, tuple):  # tuple[X, ...] fields take a TOML list too
        if not isinstance(value, (list, tuple)):
            raise CmtoolError(f"{where}{key}: expected a list, got {value!r}")
        items = [_convert(args[0], v, where, f"{key}[{i}]") for i, v in enumerate(value)]
        return items if origin is list else tuple(items)
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
    }[tp]
    if not ok:
        raise CmtoolError(f"{where}{key}: expected {tp.__name__}, got {value!r}")
    if tp is float and not math.isfinite(value):
        raise CmtoolError(f"{where}{key}: expected a finite number, got {value!r}")
    return float(value) if tp is float else value
