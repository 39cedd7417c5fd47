"""The package's import graph has no cycles.

Built from the source with ``ast`` (nothing is imported): every ``import`` and ``from
... import`` of an ``opacityhull`` module, at any depth in the file (imports inside
functions count too: a deferred import that closes a cycle is still a cycle in the
design). An edge goes to the deepest module that exists, so ``from .runner import f``
points at ``relight/runner.py`` and ``from . import runner`` at the same module; a
package's ``__init__`` is its own node.
"""

from __future__ import annotations

import ast
import functools

import pytest
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "opacityhull"


def _modules() -> dict[str, Path]:
    mods = {}
    for p in ROOT.rglob("*.py"):
        rel = p.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


def _resolve(name: str, mods: dict[str, Path]) -> str | None:
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """module → the opacityhull modules it imports (package-level names resolved)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        package = mod if is_pkg else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    stem = ".".join(base + ([node.module] if node.module else []))
                else:
                    stem = node.module or ""
                # `from pkg import sub` names a submodule when one exists
                targets = [f"{stem}.{a.name}" for a in node.names] + [stem]
                targets = [t for t in targets if t in mods] or [stem]
            for t in targets:
                if not t.startswith("opacityhull"):
                    continue
                r = _resolve(t, mods)
                # a module importing its own package's __init__ (or itself) is not a design cycle
                if r is not None and r != mod and not mod.startswith(r + ".") and r != "opacityhull":
                    graph[mod].add(r)
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_planted_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert find_cycles(g) == [["a", "b", "c"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_graph_sees_relative_and_deferred_imports():
    g = import_graph()
    assert "opacityhull.imageio" in g["opacityhull.pictures"]
    assert "opacityhull.errors" in g["opacityhull.imageio"] or "opacityhull.errors" in g["opacityhull.cliutil"]
    assert len(g) > 50


def test_no_import_cycles():
    cycles = find_cycles(import_graph())
    assert cycles == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


# --------------------------------------------------------------------------- layers

#: The packages in layer order (ARCHITECTURE.md, "Data flow"): a package may import only
#: packages of a lower rank (the same rank: none of the others). ``core`` is every
#: top-level module (camera, model, session, ...) and ``opacityhull.data``; ``demo`` is
#: ``demo.py`` / ``demo_runner.py``. ``optimize`` (#29's fitting library) sits below
#: ``reconstruct``, whose build step runs it; ``calibrate`` (a user's own cameras, #31)
#: beside it.
LAYERS: dict[str, int] = {
    "core": 0,
    "rigs": 1,
    "sim": 2,
    "acquire": 3,
    "optimize": 4,
    "calibrate": 4,
    "reconstruct": 5,
    "render": 6,
    "relight": 7,
    "evaluate": 8,
    "export": 8,
    "view": 8,
    "demo": 9,
    "cli": 10,
}

#: Lower packages a package still may not import (ARCHITECTURE.md's rules beyond the
#: order): only evaluate/, the demo and the CLI's ``--rig sim:`` reach into sim; render
#: reads only the model format.
FORBIDDEN: dict[str, set[str]] = {
    "acquire": {"sim"},
    "optimize": {"sim", "rigs", "acquire"},
    "reconstruct": {"sim", "rigs"},
    "render": {"optimize", "reconstruct", "acquire", "sim", "rigs"},
    "relight": {"sim", "rigs"},
    "export": {"sim", "rigs"},
    "view": {"sim", "rigs"},
}

#: Module arrows allowed against the rules, each with its reason (keep this short).
EXCEPTIONS: dict[tuple[str, str], str] = {
    ("opacityhull.acquire.commands", "opacityhull.sim.simrig"): "the CLI resolves --rig sim:SCENE",
    ("opacityhull.acquire.commands", "opacityhull.sim"): "the CLI resolves --rig sim:SCENE",
    ("opacityhull.acquire.commands", "opacityhull.sim.scenes"): "the CLI resolves --rig sim:SCENE (a dry run "
    "loads the scene as the capture will)",
    # the fitted splats (MODEL/optimized/) are part of the model format; their one renderer
    # is the fitting's own forward pass, reached from this one module of render/
    ("opacityhull.render.splats", "opacityhull.optimize.fit"): "the fitted splats' forward pass and loader",
    ("opacityhull.render.splats", "opacityhull.optimize.data"): "the fitted splats' model fingerprint",
    ("opacityhull.render.splats", "opacityhull.optimize.raster"): "the fitted splats with given (relit) colours",
}


def layer_of(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "core"
    name = parts[1]
    if name in ("demo", "demo_runner"):
        return "demo"
    if name == "cli":
        return "cli"
    if len(parts) == 2 and not (ROOT / name).is_dir():
        return "core"
    return "core" if name == "data" else name


def layer_violations(
    graph: dict[str, set[str]], layers=LAYERS, exceptions=EXCEPTIONS, forbidden=FORBIDDEN
) -> list[str]:
    """Every import arrow that goes up or sideways in ``layers``, or down to a package
    ``forbidden`` for the importer, as 'a -> b (la -> lb)'."""
    bad = []
    for a, targets in sorted(graph.items()):
        la = layer_of(a)
        for b in sorted(targets):
            lb = layer_of(b)
            if la == lb or (a, b) in exceptions:
                continue
            for name in (la, lb):
                if name not in layers:
                    bad.append(f"{a} -> {b}: package {name!r} is not in the layer table (tests/test_imports.py LAYERS)")
            if la in layers and lb in layers and (layers[lb] >= layers[la] or lb in forbidden.get(la, ())):
                bad.append(f"{a} -> {b} ({la} -> {lb})")
    return bad


def test_every_import_follows_the_layer_order():
    bad = layer_violations(import_graph())
    assert bad == [], "imports against the layer order (ARCHITECTURE.md):\n" + "\n".join(bad)


#: (importer, imported, allowed): arrows ARCHITECTURE.md states, checked on the rule table.
ARROWS = [
    ("opacityhull.rigs.rig", "opacityhull.sim.simrig", False),  # rigs knows nothing of sim
    ("opacityhull.sim.simrig", "opacityhull.rigs.rig", True),
    ("opacityhull.acquire.runner", "opacityhull.rigs.interfaces", True),
    ("opacityhull.acquire.commands", "opacityhull.sim.simrig", True),  # the CLI resolves --rig sim:
    ("opacityhull.reconstruct.build", "opacityhull.sim.render", False),
    ("opacityhull.reconstruct.natural_field", "opacityhull.acquire.patterns", True),
    ("opacityhull.reconstruct.holdout", "opacityhull.render.evaluate", False),  # the old render<->reconstruct pair
    ("opacityhull.render.commands", "opacityhull.reconstruct.holdout", False),
    ("opacityhull.render.renderer", "opacityhull.reconstruct.build", False),
    ("opacityhull.render.splats", "opacityhull.optimize.fit", True),  # the fitted splats' renderer
    ("opacityhull.render.runner", "opacityhull.optimize.fit", False),  # ... only through render/splats.py
    ("opacityhull.relight.runner", "opacityhull.render.renderer", True),
    ("opacityhull.relight.evaluate", "opacityhull.sim.render", False),  # only evaluate reaches into sim
    ("opacityhull.evaluate.relight", "opacityhull.sim.render", True),
    ("opacityhull.evaluate.holdout", "opacityhull.reconstruct.build", True),
    ("opacityhull.export.formats", "opacityhull.evaluate.loo", False),
    ("opacityhull.view.bundle", "opacityhull.export.formats", False),
    ("opacityhull.cli", "opacityhull.evaluate.commands", True),
    ("opacityhull.camera", "opacityhull.render.renderer", False),
]


@pytest.mark.parametrize("a, b, allowed", ARROWS, ids=[f"{a}->{b}" for a, b, _ in ARROWS])
def test_the_rule_table_decides_each_stated_arrow(a, b, allowed):
    assert (layer_violations({a: {b}}) == []) == allowed


def test_a_planted_wrong_arrow_fails(tmp_path, monkeypatch):
    """A temporary module in render/ that imports reconstruct: the graph sees it and the
    layer rule names it."""
    planted = ROOT / "render" / "_planted_wrong_arrow.py"
    planted.write_text("def f():\n    from ..reconstruct.build import build_model\n\n    return build_model\n")
    try:
        import_graph.cache_clear()
        bad = layer_violations(import_graph())
    finally:
        planted.unlink()
        import_graph.cache_clear()
    assert bad == [
        "opacityhull.render._planted_wrong_arrow -> opacityhull.reconstruct.build (render -> reconstruct)"
    ], bad


def test_no_module_is_over_1200_lines_but_the_kernel_modules():
    """numba kernel modules keep their kernels and NumPy twins together (ARCHITECTURE.md)."""
    allowed = {
        "reconstruct/matting.py": "numba: triangulation matting and drift kernels with their twins",
        "reconstruct/natural.py": "numba: NNLS box-kernel estimation with its SciPy reference",
    }
    long = {
        str(p.relative_to(ROOT)): n
        for p in ROOT.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > 1200 and str(p.relative_to(ROOT)) not in allowed
    }
    assert long == {}, long
