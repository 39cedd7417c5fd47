"""The fuzzing pass (benchmarks/fuzz.py, #35) in a quick version: a few hypothesis
mutations of every file format through the project's readers; each ends in success or
an error naming the file, never a traceback. The full pass (≥ 2,000 inputs) is
`python benchmarks/fuzz.py`, and `make bench` runs its --quick mode."""

from __future__ import annotations

import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def test_fuzz_quick_is_clean():
    sys.path.insert(0, str(BENCH))
    try:
        import fuzz
    finally:
        sys.path.remove(str(BENCH))
    rep = fuzz.run(per_format=4, cli_samples=0)
    assert rep["inputs"] == 4 * len(rep["per_format"]) and len(rep["per_format"]) == 15
    assert rep["clean"], rep["findings"]
