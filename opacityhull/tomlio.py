"""Reading TOML files: one reader that names the file, and typed getters that name the key.

Every TOML the project reads (``session.toml``, ``model.toml``, rig TOMLs, capture
plans, scene files) goes through :func:`read_toml`, so a missing file, a file that is
not text and a syntax error all read the same way and raise the error class the caller
chooses: :class:`~opacityhull.errors.FormatError` for files the pipeline wrote
(corrupt data, exit 4), :class:`~opacityhull.errors.ConfigError` for files a person
wrote (bad input, exit 2). :class:`TomlContext` checks values key by key, with messages
``"<file>: <key>: expected ..., got ..."``.

Writing goes through :func:`toml_dumps` (``tomli_w``, after turning NumPy values into
Python ones and leaving out None, which TOML cannot hold); a table whose None values
matter (``model.toml``'s ``build_config``) records them beside it with
:func:`split_nones` / :func:`join_nones`.
"""

from __future__ import annotations

import datetime
import logging
import math
import tomllib
from pathlib import Path
from typing import Any
from collections.abc import Mapping

import numpy as np

from .errors import FormatError, InputError

log = logging.getLogger(__name__)

__all__ = ["read_toml", "TomlContext", "toml_dumps", "split_nones", "join_nones"]


def _plain(v: Any, where: str) -> Any:
    """``v`` as the Python values ``tomli_w`` writes: NumPy scalars and arrays become
    numbers and lists, tuples lists, dict keys strings; None is left out of tables (TOML
    has no null) and refused inside arrays; anything else is written as its ``str``."""
    if isinstance(v, dict):
        return {str(k): _plain(x, f"{where}.{k}" if where else str(k)) for k, x in v.items() if x is not None}
    if isinstance(v, (list, tuple, np.ndarray)):
        items = v.tolist() if isinstance(v, np.ndarray) else v
        if any(x is None for x in items):
            raise InputError(f"TOML cannot store None (in the array {where or 'at the top'}); leave the key out")
        return [_plain(x, where) for x in items]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v)
    if isinstance(v, (str, datetime.date, datetime.time)):
        return v
    return str(v)


def toml_dumps(data: Mapping[str, Any]) -> str:
    """``data`` as TOML text, written by ``tomli_w``: nested tables, arrays of tables
    (lists whose items are all tables), NumPy values, NaN and ±inf; None values are left
    out (:func:`split_nones` keeps them where they matter). ``tomllib.loads`` gives the
    values back."""
    import tomli_w

    return tomli_w.dumps(_plain(dict(data), ""))


def split_nones(table: Mapping[str, Any], prefix: str = "") -> tuple[dict[str, Any], list[str]]:
    """``table`` without its None values (nested tables too), and the dotted keys that
    were None: TOML has no null, so a config whose None differs from a left-out key's
    default stores this list beside the table. :func:`join_nones` is the inverse."""
    out: dict[str, Any] = {}
    nones: list[str] = []
    for k, v in table.items():
        key = f"{prefix}{k}"
        if v is None:
            nones.append(key)
        elif isinstance(v, Mapping):
            out[k], sub = split_nones(v, key + ".")
            nones += sub
        else:
            out[k] = v
    return out, nones


def join_nones(table: Mapping[str, Any], nones) -> dict[str, Any]:
    """The inverse of :func:`split_nones`: ``table`` (copied) with each dotted key of
    ``nones`` set to None."""
    out = {k: (join_nones(v, ()) if isinstance(v, Mapping) else v) for k, v in table.items()}
    for key in nones or ():
        *path, last = str(key).split(".")
        d = out
        for p in path:
            d = d.setdefault(p, {})
        d[last] = None
    return out


def read_toml(path, *, error: type[Exception] = FormatError, what: str = "TOML file") -> dict[str, Any]:
    """Parse the TOML file at ``path``.

    Parameters
    ----------
    path : path-like
    error : exception class
        Raised (with a message naming ``path``) when the file is missing, unreadable,
        not UTF-8 text, or not valid TOML.
    what : str
        What the file is, for the "not found" message (``"rig TOML"``, ``"model.toml"``).

    Returns
    -------
    dict
        The top-level table.
    """
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise error(f"{p}: no such {what}") from None
    except IsADirectoryError:
        raise error(f"{p} is a folder, expected a {what}") from None
    except UnicodeDecodeError as e:
        raise error(f"{p}: not a text file ({e})") from None
    except OSError as e:
        raise error(f"{p}: cannot read the {what} ({e.strerror or e})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise error(f"{p}: invalid TOML ({e})") from None
    log.debug("read %s (%d top-level keys)", p, len(data))
    return data


class TomlContext:
    """Typed getters over parsed TOML tables; every error names ``source`` and the key.

    ``key`` arguments are the dotted path of the table being read (``"devices.lights"``),
    ``name`` the key inside it. A ``default`` of ``None`` makes the key required.
    """

    def __init__(self, source: str, *, error: type[Exception] = FormatError):
        self.source = str(source)
        self.error = error

    def err(self, key: str, msg: str) -> Exception:
        return self.error(f"{self.source}: {key}: {msg}")

    def table(self, key: str, v) -> dict:
        """``v`` itself, checked to be a table."""
        if not isinstance(v, dict):
            raise self.err(key, f"expected a table, got {type(v).__name__} {v!r}")
        return v

    def keys(self, key: str, d: Mapping, allowed: set[str]) -> None:
        """Refuse keys of ``d`` outside ``allowed`` (a typo must not be ignored)."""
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise self.err(key, f"unknown key(s) {unknown}; allowed: {sorted(allowed)}")

    def num(self, key: str, d: Mapping, name: str, default=None, *, positive=False, nonneg=False) -> float:
        """A finite number (int or float, not bool), optionally > 0 or >= 0."""
        if name not in d:
            if default is None:
                raise self.err(key, f"missing key {name!r}")
            return float(default)
        v = d[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.err(f"{key}.{name}", f"expected a number, got {v!r}")
        if positive and v <= 0:
            raise self.err(f"{key}.{name}", f"must be > 0, got {v}")
        if nonneg and v < 0:
            raise self.err(f"{key}.{name}", f"must be >= 0, got {v}")
        return float(v)

    def int_(self, key: str, d: Mapping, name: str, default: int | None, lo: int, hi: int) -> int:
        """An integer (not bool) in ``lo..hi``."""
        if name not in d and default is None:
            raise self.err(key, f"missing key {name!r}")
        v = d.get(name, default)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise self.err(f"{key}.{name}", f"expected an integer in {lo}..{hi}, got {v!r}")
        return int(v)

    def _given(self, key: str, d: Mapping, name: str, default):
        """``(d[name], True)``, or ``(default, False)`` when absent; absent without a default is an error."""
        if name in d:
            return d[name], True
        if default is None:
            raise self.err(key, f"missing key {name!r}")
        return default, False

    def str_(self, key: str, d: Mapping, name: str, default: str | None = None) -> str:
        """A string."""
        v, given = self._given(key, d, name, default)
        if given and not isinstance(v, str):
            raise self.err(f"{key}.{name}", f"expected a string, got {v!r}")
        return v

    def bool_(self, key: str, d: Mapping, name: str, default: bool | None = None) -> bool:
        """A boolean (``true``/``false``, not 0/1)."""
        v, given = self._given(key, d, name, default)
        if given and not isinstance(v, bool):
            raise self.err(f"{key}.{name}", f"expected true or false, got {v!r}")
        return v
