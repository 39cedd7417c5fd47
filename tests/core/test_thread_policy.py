"""`import opacityhull` makes idle OpenMP threads sleep unless the user chose otherwise
(ARCHITECTURE.md, pitfalls: spinning numba threads on a contended machine)."""

from __future__ import annotations

import os
import subprocess
import sys


def _policy_after_import(env_value: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_value is not None:
        env["OMP_WAIT_POLICY"] = env_value
    code = "import os, opacityhull; print(os.environ.get('OMP_WAIT_POLICY', '<unset>'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_passive_by_default():
    assert _policy_after_import(None) == "PASSIVE"


def test_user_setting_wins():
    assert _policy_after_import("ACTIVE") == "ACTIVE"
