"""`kill -USR1` on a running `opacityhull` prints every thread's stack and does not stop it
(opacityhull/cli.py: main registers faulthandler; tests/e2e/test_capture_resume.py uses
it to say where a stuck child waits)."""

from __future__ import annotations

import subprocess
import sys

CODE = """
import os, signal, sys
import opacityhull.cli as cli
sys.argv = ["opacityhull", "--help"]
try:
    cli.main()
except SystemExit:
    pass
os.kill(os.getpid(), signal.SIGUSR1)
print("still running")
"""


def test_sigusr1_dumps_stacks_and_the_process_goes_on():
    r = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().endswith("still running")
    assert "most recent call first" in r.stderr and "<string>" in r.stderr
