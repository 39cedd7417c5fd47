"""Where a command may write: never over what it reads, and ``--overwrite`` only over
what it wrote itself.

Two rules every writing command follows, through these helpers:

- :func:`check_output` — an output equal to an input (model, session, image, map) or
  inside an input folder is refused with exit 2 before any work; an output folder that
  would be *replaced* as a whole (``export``, ``view --out``) must not contain an input
  either (``export M --out . --overwrite`` would delete ``./M``).
- :func:`written_manifest` / :func:`check_replaceable` — a folder a command replaces
  holds ``.opacityhull-written.json``, the list of the files that command wrote there.
  ``--overwrite`` replaces the folder only when every file in it is on that list; a file
  the command did not write (a model, photographs, notes) makes it exit 2 naming the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from collections.abc import Iterable, Mapping

from .errors import InputError

__all__ = ["WRITTEN", "check_output", "check_replaceable", "written_manifest", "write_written_manifest"]

#: The manifest of the files a command wrote into a folder it owns.
WRITTEN = ".opacityhull-written.json"


def _resolved(p) -> Path:
    return Path(os.path.abspath(Path(p).expanduser())).resolve()


def check_output(
    out,
    inputs: Mapping[str, object],
    *,
    flag: str = "--out",
    replaces: bool = False,
    writes: Iterable[str] = (),
) -> None:
    """Refuse (:class:`InputError`, exit 2) an output ``out`` that is an input or lies
    inside an input folder.

    Parameters
    ----------
    out : path
        The output (file or folder).
    inputs : mapping of str to path or None
        What the command reads, keyed by how the user named it (``"MODEL"``, ``"--envmap"``);
        None entries (options left out) and ``builtin:`` names are skipped.
    replaces : bool
        ``out`` is replaced as a whole: an input inside it is refused as well.
    writes : iterable of str
        Names of the files the command writes inside the folder ``out``; one that is an
        input file is refused (``matte --out .`` over a photograph called ``alpha.png``).
    """
    o = _resolved(out)
    for name, p in inputs.items():
        if p is None or (isinstance(p, str) and ":" in p and not Path(p).exists()):
            continue
        i = _resolved(p)
        what = f"the input {name} ({p})"
        if o == i:
            raise InputError(
                f"{flag} {out}: is {what}; the command would write over what it reads — choose another {flag}"
            )
        if i in o.parents:
            raise InputError(f"{flag} {out}: is inside {what}; choose a {flag} outside it (nothing was written)")
        if replaces and o in i.parents:
            raise InputError(
                f"{flag} {out}: contains {what}, and replacing {flag} would delete it — choose another {flag}"
            )
        for w in writes:
            if o / w == i:
                raise InputError(f"{flag} {out}: {w} would be written over {what} — choose another {flag}")


def written_manifest(folder) -> dict | None:
    """The manifest of ``folder`` (``{"command": str, "files": [relative paths]}``), or
    None when there is none or it cannot be read."""
    p = Path(folder) / WRITTEN
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict) or not isinstance(d.get("files"), list) or not isinstance(d.get("command"), str):
        return None
    return d


def write_written_manifest(folder, *, command: str) -> None:
    """List every file under ``folder`` as written by ``command`` (call when the folder is
    complete, before it is renamed into place)."""
    folder = Path(folder)
    files = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() and p.name != WRITTEN)
    (folder / WRITTEN).write_text(json.dumps({"command": command, "files": files}, indent=1) + "\n", encoding="utf-8")


def check_replaceable(out, *, command: str, overwrite: bool, flag: str = "--out", legacy=None) -> None:
    """Refuse replacing ``out`` unless it is absent, empty, or (with ``overwrite``) holds
    only files that ``command`` wrote there before (its :data:`WRITTEN` manifest).

    ``legacy(out)`` may accept an older output of the same command written before
    manifests existed (the viewer bundle's own ``manifest.json``)."""
    out = Path(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise InputError(f"{flag} {out}: is an existing file, expected a folder — choose another {flag}")
    present = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file() and p.name != WRITTEN)
    if not present:  # nothing but empty folders: nothing to lose
        return
    if not overwrite:
        raise InputError(f"{flag} {out}: exists and is not empty (pass --overwrite to replace an earlier {command})")
    man = written_manifest(out)
    if man is None or man["command"] != command:
        if legacy is not None and legacy(out):
            return
        raise InputError(
            f"{flag} {out}: --overwrite replaces only an earlier `{command}` output, and this folder has no record "
            f"of one ({WRITTEN}); it holds {len(present)} file(s) such as {present[:3]} — choose another {flag}"
        )
    foreign = sorted(set(present) - set(man["files"]))
    if foreign:
        raise InputError(
            f"{flag} {out}: --overwrite replaces only what `{command}` wrote there, and {len(foreign)} file(s) are "
            f"not its own, e.g. {foreign[:3]} — move them or choose another {flag}"
        )
