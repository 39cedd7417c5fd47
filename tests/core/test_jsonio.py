"""to_jsonable: the one JSON conversion, importable without the CLI's dependencies."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from opacityhull.jsonio import to_jsonable


def test_numpy_paths_and_non_finite_values_become_plain_json():
    got = to_jsonable(
        {1: np.float32(0.5), "a": np.arange(3), "p": Path("x/y"), "t": (np.int64(2), float("nan"), -np.inf)}
    )
    assert got == {"1": 0.5, "a": [0, 1, 2], "p": "x/y", "t": [2, None, None]}
    assert json.loads(json.dumps(got, allow_nan=False)) == got


def test_the_library_module_does_not_pull_the_cli():
    code = "import sys, opacityhull.jsonio; sys.exit(int('typer' in sys.modules or 'rich' in sys.modules))"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0
