"""CLI rough edges: messages keep their brackets, --json takes a boolean word, shell
completion exists, human text goes to stderr, and what an unexpected OSError becomes."""

from __future__ import annotations

import json

import pytest

from badkit import Case, flat, invoke, run_case

GEOMETRY_NO_CAMERAS = """
[geometry]
target_m = [0.0, 0.1, 0.0]
cameras = []
"""

PLAN_UNKNOWN_KEY = """
[plan]
name = "p"
[table]
steps = 2
[phases.matting]
patterns = 1
bogus = 3
"""


def _write(name: str, text: str):
    def setup(root):
        (root / name).write_text(text)

    return setup


CASES = [
    # rich would eat "[[rig.cameras]]" / "[phases.matting]" as markup: the user saw "at least one [] entry"
    Case(
        "markup-double-brackets",
        ("capture", "--rig", "{T}/rig.toml", "--plan", "builtin:tiny", "--dry-run"),
        2,
        r"at least one \[\[.*geometry.cameras\]\] entry is required",
        setup=_write("rig.toml", GEOMETRY_NO_CAMERAS),
    ),
    Case(
        "markup-plan-table",
        ("capture", "--rig", "sim:builtin:diffuse", "--plan", "{T}/plan.toml", "--dry-run"),
        2,
        r"plan.toml: \[phases.matting\]: unknown key\(s\) \['bogus'\]",
        setup=_write("plan.toml", PLAN_UNKNOWN_KEY),
    ),
    Case("json-bad-word", ("session", "info", "{T}/nosuch", "--json=maybe"), 2, r"(?i)json"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_cli_input(case, tmp_path):
    run_case(case, inputs={}, tmp_path=tmp_path)


@pytest.mark.parametrize(
    "words, is_json",
    [
        (["--json"], True),
        (["--json", "true"], True),
        (["--json=yes"], True),
        (["--json", "false"], False),
        (["--json=0"], False),
        ([], False),
    ],
)
def test_json_accepts_a_boolean_word(session_dir, words, is_json):
    r = invoke(["session", "info", session_dir, *words])
    assert r.exit_code == 0, r.output
    if is_json:
        assert json.loads(r.stdout)["session"] == str(session_dir)
    else:
        # session info's job is to print: its text is on stdout (#33), only notes on stderr
        assert r.stdout.startswith("session ") and "note:" not in r.stderr


def test_normalize_argv_only_touches_the_json_flag():
    from opacityhull.cli import normalize_argv

    assert normalize_argv(["render", "m", "--out", "true", "--json", "no"]) == ["render", "m", "--out", "true"]
    assert normalize_argv(["x", "--json", "on", "y"]) == ["x", "--json", "y"]


def test_shell_completion_is_enabled():
    r = invoke(["--help"])
    assert "--install-completion" in r.stdout and "--show-completion" in r.stdout
    r = invoke(["--show-completion", "bash"])
    assert r.exit_code == 0 and "_OPACITYHULL_COMPLETE" in r.stdout.upper(), r.output


def test_redirected_stdout_gets_a_hint_on_stderr(monkeypatch, capsys):
    """`session info > f` left an empty file and no reason: the result is on stderr."""
    import sys

    from opacityhull import cliutil

    monkeypatch.delenv("OPACITYHULL_NO_HINT", raising=False)
    monkeypatch.setattr(sys.stdout, "isatty", lambda: False, raising=False)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    cliutil.emit({"a": 1}, False, lambda s: None)
    err = capsys.readouterr().err
    assert "stdout is for --json" in err


def test_unexpected_os_errors_become_messages_not_tracebacks():
    import errno

    import typer

    from opacityhull.cliutil import _known_error, cli_errors
    from opacityhull.errors import InputError, WriteError

    e = _known_error(OSError(errno.ENOSPC, "No space left on device", "/data/m/x.exr"))
    assert isinstance(e, WriteError) and "/data/m/x.exr" in str(e) and "disk is full" in str(e)
    e = _known_error(OSError(errno.EROFS, "Read-only file system", "/mnt/ro/a"))
    assert isinstance(e, WriteError) and "read-only" in str(e) and e.exit_code == 2
    e = _known_error(FileNotFoundError(errno.ENOENT, "No such file or directory", "/x/y"))
    assert isinstance(e, InputError) and e.exit_code == 2 and "/x/y" in str(e)
    assert _known_error(OSError(errno.EIO, "I/O error")) is None  # a real fault stays visible

    @cli_errors
    def cmd():
        raise OSError(errno.ENOSPC, "No space left on device", "/d/f")

    with pytest.raises(typer.Exit) as ei:
        cmd()
    assert ei.value.exit_code == 2


def test_terminated_maps_to_128_plus_signal():
    import signal

    import typer

    from opacityhull.cliutil import cli_errors
    from opacityhull.errors import Terminated

    for sig, code in ((signal.SIGTERM, 143), (signal.SIGHUP, 129)):

        @cli_errors
        def cmd(sig=sig):
            raise Terminated(sig)

        with pytest.raises(typer.Exit) as ei:
            cmd()
        assert ei.value.exit_code == code
    assert isinstance(Terminated(15), KeyboardInterrupt) and str(Terminated(15)) == "terminated by SIGTERM"


def test_capture_dry_run_checks_the_devices_like_rig_check(tmp_path):
    """A rig TOML whose geometry parses but whose [devices] a real capture refuses."""
    from pathlib import Path

    example = Path(__file__).resolve().parents[2] / "examples" / "rig-emulated.toml"
    bad = tmp_path / "rig.toml"
    text = example.read_text()
    assert "[devices.turntable]" in text
    bad.write_text(text.replace("[devices.turntable]", "[devices.turntable]\nbogus_key = 1", 1))
    r = invoke(["capture", "--rig", bad, "--plan", "builtin:tiny", "--dry-run"])
    assert r.exit_code == 2, r.output
    assert "bogus_key" in flat(r.stderr) and "devices.turntable" in flat(r.stderr)
    ok = invoke(["capture", "--rig", example, "--plan", "builtin:tiny", "--dry-run", "--json"])
    assert ok.exit_code == 0 and json.loads(ok.stdout)["dry_run"] is True
