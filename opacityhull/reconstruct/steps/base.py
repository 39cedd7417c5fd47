"""The build step interface: a :class:`Step` is a name, the :class:`BuildContext` fields it
reads (``inputs``) and the one it sets (``product``), and ``run(ctx)``. A step that makes
something worth keeping between builds goes through :func:`..buildstore.cached` inside
``run`` (its key: the digests of its inputs and its parameters), so ``build --resume``
reuses it and verifies what it reuses. ``opacityhull.reconstruct.build.STEPS`` is the
ordered list; :func:`check_steps` checks that every input is made by an earlier step.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any
from collections.abc import Callable, Sequence

from ...errors import InputError

__all__ = ["Step", "BuildContext", "check_steps"]


@dataclass(frozen=True, kw_only=True)
class Step:
    """One build step.

    name : the step's name in ``report.json``'s ``steps``/``seconds`` and in the manifest.
    run : ``run(ctx)`` reads ``ctx.<input>`` for each of ``inputs`` and sets ``ctx.<product>``.
    inputs : the :class:`BuildContext` fields it reads (products of earlier steps, or
        the fields every build starts with: session, out, config, ...).
    product : the field it sets (None: it only writes files or the report).
    params : the :class:`~..buildconfig.BuildConfig` fields that shape its product
        (documentation: the step's key in :func:`..buildstore.cached` is what counts).
    """

    name: str
    run: Callable[[BuildContext], None]
    inputs: tuple[str, ...] = ()
    product: str | None = None
    params: tuple[str, ...] = ()


@dataclass(kw_only=True)
class BuildContext:
    """What the steps of one build hand down: the fixed inputs of the build, then one
    field per step product (None until the step has run)."""

    # the build's inputs
    session: Any
    out: Path
    config: Any
    store: Any
    timer: Any
    progress: Callable[[int, int], None]
    executor: Any = None
    ground_truth: bool = False
    budget_gb: float = 0.0
    notes: list = field(default_factory=list)
    nonfinite: list = field(default_factory=list)
    # products, in step order
    cameras: Any = None  # steps.cameras.CameraProduct
    plan: Any = None  # lazyviews.MemoryPlan
    split: Any = None  # steps.split.Split
    mattes: Any = None  # lazyviews.Mattes
    holes: Any = None  # steps.holes.HolesProduct
    geometry: Any = None  # steps.geometry.GeometryProduct
    reflectance: Any = None  # (reflectance or None, digest)
    natural: Any = None  # (natural field summary or None, key)
    model: Any = None  # steps.write.WriteProduct
    fit: Any = None  # steps.optimize: report.json's "optimize" (dict)
    pictures: Any = None  # list of picture paths
    metrics: Any = None  # dict
    report: Any = None  # BuildReport

    def finite(self, img, where: str):
        """``img`` with its NaN/Inf counted into the report's notes (``session.check_finite``)."""
        from ...session import check_finite

        n = check_finite(img, where=where)
        if n and len(self.nonfinite) < 1000:
            self.nonfinite.append(n)
        return img


_START = ("session", "out", "config", "store", "timer", "progress", "executor", "ground_truth", "budget_gb", "notes")


def check_steps(steps: Sequence[Step]) -> None:
    """Raise InputError unless step names are unique, every product is a
    :class:`BuildContext` field set by one step, and every input is a field the build
    starts with or the product of an earlier step."""
    known = {f.name for f in fields(BuildContext)}
    have = set(_START) | {"nonfinite"}
    names: set[str] = set()
    for s in steps:
        if s.name in names:
            raise InputError(f"build step {s.name!r} is listed twice")
        names.add(s.name)
        for i in s.inputs:
            if i not in have:
                raise InputError(f"build step {s.name!r} reads {i!r}, which no earlier step makes")
        if s.product is not None:
            if s.product not in known:
                raise InputError(f"build step {s.name!r} makes {s.product!r}, which is no BuildContext field")
            if s.product in have:
                raise InputError(f"build step {s.name!r} makes {s.product!r}, already made before it")
            have.add(s.product)
