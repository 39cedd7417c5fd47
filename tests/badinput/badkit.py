"""Helpers of the bad-input suite (tests/badinput): one parametrised table per command family.

Each case is a row: the command line (in-process through :class:`typer.testing.CliRunner`
— a subprocess costs ~1.5 s of imports), a setup that breaks one thing in a copy of a
tiny synthetic session or model, the exit code expected (2 bad input, 4 corrupt data),
a regex the one-line message must match (naming the file, key, flag or value), and a
check that nothing was written or lost. ``pytest tests/badinput -q`` prints the count.

Fixtures (conftest.py) are analytic and fast (no Mitsuba).
"""

from __future__ import annotations

import hashlib
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable


@dataclass(frozen=True)
class Case:
    """One bad input: ``argv`` may contain ``{S}`` (the session copy), ``{M}`` (the model
    copy) and ``{T}`` (the test's tmp folder); ``setup(root)`` breaks the copy."""

    id: str
    argv: tuple
    code: int
    message: str
    setup: Callable[[Path], None] | None = None
    must_not_exist: tuple = ()  # paths (with the same placeholders) the command must not create
    unchanged: bool = True  # the input folder's files are byte-identical afterwards
    extra: dict = field(default_factory=dict)


def tree_digest(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (relative POSIX path → hex)."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        if p.is_file():
            out[p.relative_to(root).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def flat(text: str) -> str:
    """Output without rich's line wrapping."""
    return " ".join(text.split())


def invoke(argv):
    """Run the real CLI app in-process; returns the click Result (stdout/stderr apart)."""
    from typer.testing import CliRunner

    from opacityhull.cli import app, normalize_argv

    # a wide terminal: rich would otherwise break long paths inside the messages
    return CliRunner().invoke(app, normalize_argv([str(a) for a in argv]), env={"COLUMNS": "4000"})


def run_case(case: Case, *, inputs: dict[str, Path], tmp_path: Path):
    """Copy the inputs, apply ``case.setup``, run, and check exit code, message, no
    traceback, nothing created and inputs unchanged. Returns the result."""
    subst = {"T": str(tmp_path)}
    roots = {}
    for key, src in inputs.items():
        dst = tmp_path / key
        shutil.copytree(src, dst)
        subst[key] = str(dst)
        roots[key] = dst
    if case.setup is not None:
        case.setup(roots.get("S") or roots.get("M") or tmp_path)
    before = {k: tree_digest(r) for k, r in roots.items()}
    argv = [a.format(**subst) for a in case.argv]
    res = invoke(argv)
    text = flat(res.stderr)
    assert res.exit_code == case.code, f"{argv}: exit {res.exit_code}, expected {case.code}\n{res.output}"
    assert re.search(case.message, text), f"{argv}: message {text!r} does not match {case.message!r}"
    assert "Traceback" not in res.output, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), f"{argv}: {res.exception!r}"
    for p in case.must_not_exist:
        assert not Path(p.format(**subst)).exists(), f"{argv}: created {p}"
    if case.unchanged:
        for k, r in roots.items():
            assert tree_digest(r) == before[k], f"{argv}: changed files in {k}"
    return res
