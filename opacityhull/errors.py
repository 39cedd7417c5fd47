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


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised like Ctrl-C so that the same clean-up runs (a capture
    leaves the rig safe and the session resumable). The CLI exits 128 + ``signum``."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def signame(self) -> str:
        import signal

        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    def __str__(self) -> str:
        return f"terminated by {self.signame}"


#: Exit codes used by the CLI. 0 = success, 130 = interrupted by Ctrl-C.
EXIT_CODES = {
    "ok": 0,
    "failure": 1,
    "bad_input": 2,
    "device": 3,
    "data": 4,
    "incomplete": 5,
    "interrupted": 130,
    "hangup": 129,
    "terminated": 143,
}


def check_shape(name: str, array, expected: tuple, *, dtype=None) -> None:
    """Raise :class:`ShapeError` unless ``array.shape`` matches ``expected``.

    ``expected`` may contain ``None`` for "any size" in that axis.
    """
    shape = getattr(array, "shape", None)
    ok = (
        shape is not None
        and len(shape) == len(expected)
        and all(e is None or e == s for s, e in zip(shape, expected, strict=True))
    )
    if not ok:
        want = "(" + ", ".join("*" if e is None else str(e) for e in expected) + ")"
        raise ShapeError(f"{name} has shape {shape}, expected {want}")
    if dtype is not None and array.dtype != dtype:
        raise ShapeError(f"{name} has dtype {array.dtype}, expected {dtype}")


class WriteError(InputError):
    """An output could not be written: the disk is full, the file system read-only, or
    permission is denied. Bad input in the sense that the user must pick another place
    (or free space); what was already written stays intact."""


#: errno values that mean "this place cannot take the output", with the words for them.
WRITE_ERRNOS = {
    28: "the disk is full (ENOSPC)",
    122: "the disk quota is exceeded (EDQUOT)",
    30: "the file system is read-only (EROFS)",
    13: "permission denied (EACCES)",
    1: "operation not permitted (EPERM)",
}


def _fs_problem(path) -> str | None:
    """What is wrong with the file system holding ``path`` for writing, or None."""
    import os
    from pathlib import Path

    p = Path(path)
    for d in (p, *p.parents):
        if d.exists():
            break
    else:
        return None
    try:
        st = os.statvfs(d)
    except OSError:
        return None
    if st.f_flag & getattr(os, "ST_RDONLY", 1):
        return WRITE_ERRNOS[30]
    if st.f_bavail * st.f_frsize < (1 << 20):  # < 1 MiB left: a write that failed ran out of room
        return WRITE_ERRNOS[28]
    if not os.access(d if d.is_dir() else d.parent, os.W_OK):
        return WRITE_ERRNOS[13]
    return None


def write_error(exc: BaseException, path=None) -> WriteError | None:
    """The :class:`WriteError` for ``exc`` raised while writing ``path``, or None.

    ``OSError`` with ENOSPC/EDQUOT/EROFS/EACCES/EPERM becomes a message naming the path
    and the cause. Other exceptions (codecs such as OpenEXR raise ``RuntimeError`` and
    OpenCV returns False on a full disk) are attributed to the file system only when
    ``path``'s file system is actually full, read-only or not writable.
    """
    if isinstance(exc, WriteError):
        return exc
    where = path if path is not None else getattr(exc, "filename", None)
    why = None
    if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
        why = WRITE_ERRNOS[exc.errno]
        where = where if where is not None else exc.filename
    elif (
        where is not None
        and not isinstance(exc, OSError)
        and (not isinstance(exc, OpacityHullError) or isinstance(exc, FormatError))
    ):
        # another OSError (EIO, ENOENT) is its own message, whatever the disk's state
        why = _fs_problem(where)
    if why is None:
        return None
    what = f"cannot write {where}" if where is not None else "cannot write the output"
    return WriteError(f"{what}: {why} — {_advice(why)}; files already written are intact")


def _advice(why: str, flag: str = "--out") -> str:
    """What to do about ``why`` (one of :data:`WRITE_ERRNOS`' words): a read-only disk is
    not helped by freeing space."""
    if "read-only" in why:
        return f"remount it read-write or choose another {flag}"
    if "permission" in why or "not permitted" in why:
        return f"choose a {flag} you may write to"
    return f"free space or choose another {flag}"


def check_writable(path, *, flag: str = "--out") -> None:
    """Raise :class:`WriteError` now if ``path`` (or its nearest existing parent) is on a
    read-only or full file system, or not writable — before hours of work are spent on
    an output that cannot be saved. Creates nothing."""
    why = _fs_problem(path)
    if why is not None:
        raise WriteError(f"{flag} {path}: cannot write there: {why} — {_advice(why, flag)}")
