"""Quick benchmark runs write untracked files (#33): ``benchmarks/render.py --quick``
rewrote the tracked tables in ``benchmarks/out/``. The rule is one place,
``benchkit.out_dir``; every script takes its ``OUT`` from it."""

from __future__ import annotations

import ast
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def test_quick_runs_write_under_an_ignored_folder():
    import importlib.util

    spec = importlib.util.spec_from_file_location("benchkit", BENCH / "benchkit.py")
    assert spec is not None and spec.loader is not None
    benchkit = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(benchkit)
    assert benchkit.out_dir(["--quick", "--json"]) == BENCH / "out" / "quick"
    assert benchkit.out_dir(["--json"]) == BENCH / "out"
    ignored = (BENCH.parent / ".gitignore").read_text().split()
    assert "benchmarks/out/quick/" in ignored or "benchmarks/out/" in ignored


def test_every_benchmark_takes_its_out_folder_from_benchkit():
    for script in sorted(BENCH.glob("*.py")):
        if script.name == "benchkit.py":
            continue
        tree = ast.parse(script.read_text())
        outs = [
            n.value
            for n in tree.body
            if isinstance(n, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "OUT" for t in n.targets)
        ]
        if not outs:
            # a benchmark that only prints (fuzz.py, build_digest.py) writes no report
            assert '"out"' not in script.read_text(), f"{script.name}: writes under out/ without OUT = out_dir()"
            continue
        v = outs[0]
        assert isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id == "out_dir", script.name
