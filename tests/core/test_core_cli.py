"""The root CLI: every command and group answers --help, --version works."""

import subprocess
import sys

from typer.testing import CliRunner

from opacityhull import __version__
from opacityhull.cli import GROUPS, app


def test_version():
    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output


def test_every_command_has_help():
    import typer.main

    click_app = typer.main.get_command(app)
    runner = CliRunner()
    seen = 0
    for name, cmd in click_app.commands.items():
        r = runner.invoke(app, [name, "--help"])
        assert r.exit_code == 0, (name, r.output)
        seen += 1
        for sub in getattr(cmd, "commands", {}):
            r = runner.invoke(app, [name, sub, "--help"])
            assert r.exit_code == 0, (name, sub, r.output)
            assert "Usage" in r.output
    assert seen >= len(GROUPS)


def test_console_script_entry_point():
    r = subprocess.run([sys.executable, "-m", "opacityhull.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "opacityhull" in r.stdout
