"""Build step ``natural``: the natural-illumination reflectance field (Matusik, Loper &
Pfister 2004) of each view and display, from the session's natural-image shots
(:func:`..natural_field.estimate_session_natural`), written to ``MODEL/natural/``."""

from __future__ import annotations

from ...errors import FormatError
from ...model import BUILD_DIR
from ..buildstore import _digest, _records_digest, cached, pop_timings
from .base import Step


def plan_kernels(session, configured: int | None) -> int:
    """K of the estimate: the build's ``natural_kernels`` if set, else the session plan's
    ``[phases.natural] kernels`` (25, the paper's, when the plan does not say)."""
    if configured is not None:
        return int(configured)
    phases = (session.plan or {}).get("phases", {}) or {}
    ph = phases.get("natural") or phases.get("envmatte") or {}
    k = ph.get("kernels", 25) if isinstance(ph, dict) else 25
    if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 255:
        raise FormatError(
            f"{session.root / 'session.toml'}: [plan.phases.natural] kernels = {k!r}, expected an integer in [1, 255]"
        )
    return k


def run(ctx) -> None:
    session, config, out = ctx.session, ctx.config, ctx.out
    natural, natural_key = None, ""
    with ctx.timer.step("natural"):
        if config.natural and ("envmatte" in session.phases() or "natural" in session.phases()):
            from ..natural_field import estimate_session_natural

            nat_recs = [
                r
                for ph in ("envmatte", "natural")
                if ph in session.phases()
                for r in session.select(phase=ph, kind=None)
            ]
            n_kernels = plan_kernels(session, config.natural_kernels)
            nat_in = {
                "images": _digest(_records_digest(session, nat_recs)),
                "mattes": ctx.mattes.content,
                "cameras": ctx.cameras.key,
            }

            def estimate():
                out.mkdir(parents=True, exist_ok=True)
                got = estimate_session_natural(
                    session,
                    ctx.cameras.views,
                    ctx.cameras.cams.views,
                    ctx.mattes.alphas,
                    out,
                    n_kernels=n_kernels,
                    progress=ctx.progress,
                )
                ctx.timer.detail["natural"] = pop_timings(got)  # the pickle carries no time
                return got

            got = cached(
                ctx.store,
                "natural",
                inputs=nat_in,
                params={"n_kernels": n_kernels},
                run=estimate,
                pickle_as=f"{BUILD_DIR}/natural.pkl",
                expect=dict,
                outputs=["natural"],
            )
            natural, natural_key = got.value, got.key
    ctx.natural = (natural, natural_key)


STEP = Step(
    name="natural",
    run=run,
    inputs=("session", "cameras", "mattes", "config", "store"),
    product="natural",
    params=("natural", "natural_kernels"),
)
