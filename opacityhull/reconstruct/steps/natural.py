"""Build step ``natural``: the natural-illumination reflectance field (Matusik, Loper &
Pfister 2004) of each view and display, from the session's natural-image shots
(:func:`..natural_field.estimate_session_natural`), written to ``MODEL/natural/``."""

from __future__ import annotations

from ...model import BUILD_DIR
from ..buildstore import _digest, _records_digest, cached, pop_timings
from .base import Step


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
                    n_kernels=config.natural_kernels,
                    progress=ctx.progress,
                )
                ctx.timer.detail["natural"] = pop_timings(got)  # the pickle carries no time
                return got

            got = cached(
                ctx.store,
                "natural",
                inputs=nat_in,
                params={"n_kernels": config.natural_kernels},
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
