"""Build step ``split``: the train/test protocol of nerfstudio and the NeRF papers
(``build --hold-out every:N | VIEW,...``). Held-out views keep their cameras and
photographs in the model, but no step that shapes it sees them: the geometry step
builds hull, surfels, visibility and refinement from the training views, and the
held-out views' visibility bits stay clear, so no renderer blends them
(``eval test`` renders them)."""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Sequence

from ...errors import InputError
from .base import Step

__all__ = ["Split", "every_step", "resolve_hold_out", "STEP"]


@dataclass(frozen=True, kw_only=True)
class Split:
    """Indices (in the model's view order) of the training and the held-out views."""

    train: tuple[int, ...]
    held_out: tuple[int, ...]
    spec: str | None = None


def every_step(spec: str, *, flag: str, need: str) -> int:
    """N of an ``every:N`` view selection (``spec`` starts with ``every:``); an N that is
    not a whole number >= 1 is an :class:`InputError` naming ``flag`` and ``need``."""
    try:
        step = int(spec.strip()[6:])
    except ValueError:
        step = 0
    if step < 1:
        raise InputError(f"{flag}: every:N needs {need}")
    return step


def resolve_hold_out(spec: str | None, view_ids: Sequence[str]) -> tuple[int, ...]:
    """The held-out view indices of ``build --hold-out SPEC`` over the build's views:
    ``every:N`` (views 0, N, 2N, ...; N >= 2) or a comma list of view ids and/or
    indices. An empty or unknown selection, an index out of range, or one that holds out
    every view is an :class:`InputError` naming ``--hold-out`` (nothing is written)."""
    V = len(view_ids)
    if spec is None:
        return ()
    s = str(spec).strip()
    flag = f"--hold-out {spec!r}"
    if s.startswith("every:"):
        step = every_step(s, flag=flag, need="a whole number N >= 2 (every N-th view is a test view)")
        held = tuple(range(0, V, step))
    else:
        items = [t.strip() for t in s.split(",") if t.strip()]
        if not items:
            raise InputError(f"{flag}: names no view; expected every:N or a comma list of view ids or indices")
        index = {v: i for i, v in enumerate(view_ids)}
        out: list[int] = []
        for it in items:
            if it.isdigit():
                i = int(it)
                if not 0 <= i < V:
                    raise InputError(f"{flag}: view index {i} is out of range [0, {V})")
            elif it in index:
                i = index[it]
            else:
                near = ", ".join(list(view_ids)[:3])
                raise InputError(f"{flag}: no view {it!r} in the session (views are named like {near}, ...)")
            if i not in out:
                out.append(i)
        held = tuple(sorted(out))
    if not held:
        raise InputError(f"{flag}: names no view of the {V}")
    if len(held) >= V:
        raise InputError(f"{flag}: holds out all {V} views; at least one must be left to build from")
    return held


def run(ctx) -> None:
    held = resolve_hold_out(ctx.config.hold_out, ctx.cameras.vids)
    train = tuple(i for i in range(len(ctx.cameras.vids)) if i not in set(held))
    ctx.split = Split(train=train, held_out=held, spec=ctx.config.hold_out)
    if held:
        ctx.notes.append(
            f"hold-out ({ctx.config.hold_out}): {len(held)} test view(s) kept out of the geometry and the "
            f"blending, {len(train)} built from: " + ", ".join(ctx.cameras.vids[i] for i in held)
        )


STEP = Step(name="split", run=run, inputs=("cameras", "config"), product="split", params=("hold_out",))
