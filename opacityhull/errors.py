"""Exception hierarchy shared by every stage.

Every error the user can cause or fix carries a message that names the file, flag,
key or device involved and what was expected. The CLI maps the classes to exit codes
(see :data:`EXIT_CODES`), so scripts can tell bad input from a broken device from
corrupt data.
"""

from __future__ import annotations


class OpacityHullError(Exception):
    """Base class of every error raised on purpose by opacityhull."""

    exit_code = 1


class InputError(OpacityHullError, ValueError):
    """Bad input: a value, shape, flag or file that does not match what is expected."""

    exit_code = 2


class ShapeError(InputError):
    """An array has the wrong shape or dtype; the message gives actual and expected."""


class ConfigError(InputError):
    """A TOML config (rig, plan, scene) has a missing, unknown or invalid key."""


class FormatError(OpacityHullError):
    """A file on disk is missing, truncated, corrupt or of an unknown format version."""

    exit_code = 4


class DeviceError(OpacityHullError):
    """A rig device failed: no answer, garbled answer, alarm, or vanished port."""

    exit_code = 3


class CaptureInterrupted(OpacityHullError):
    """A capture stopped before its plan was complete; it can be resumed."""

    exit_code = 5


#: Exit codes used by the CLI. 0 = success, 130 = interrupted by Ctrl-C.
EXIT_CODES = {
    "ok": 0,
    "failure": 1,
    "bad_input": 2,
    "device": 3,
    "data": 4,
    "incomplete": 5,
    "interrupted": 130,
}


def check_shape(name: str, array, expected: tuple, *, dtype=None) -> None:
    """Raise :class:`ShapeError` unless ``array.shape`` matches ``expected``.

    ``expected`` may contain ``None`` for "any size" in that axis.
    """
    shape = getattr(array, "shape", None)
    ok = shape is not None and len(shape) == len(expected) and all(
        e is None or e == s for s, e in zip(shape, expected)
    )
    if not ok:
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
        raise ShapeError(f"{name} has shape {shape}, expected {want}")
    if dtype is not None and array.dtype != dtype:
        raise ShapeError(f"{name} has dtype {array.dtype}, expected {dtype}")
