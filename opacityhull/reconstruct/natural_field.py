"""Build step "natural": reflectance fields from natural illumination, per view and display.

For every view (camera, table angle) and every illumination domain (a display that
showed the natural phase's images while the others were black), the photographs
``B`` (radiance, :meth:`Session.load_radiance`) of the pixels inside the matte
(α > ``alpha_min``, default 0.5, grown through connected α > 0.1, enclosed holes filled: :func:`natural_mask`) and the shown images ``L`` (display radiance: the uploaded 8-bit
pattern as linear drive × the display's ``max_radiance``, what the sim emits and a
linearised real display shows) go through :func:`opacityhull.reconstruct.natural.estimate_natural`
(K box kernels per pixel, NNLS weights). Each result is written as
``MODEL/natural/<view_id>/<display>.npz`` (:func:`~opacityhull.reconstruct.natural.save_field`,
with ``pixel_index`` / ``image_hw`` locating the matte pixels in the view).

The capture runner records the phase as ``envmatte`` (the plan's ``[phases.natural]``
under its older name); a session whose records say ``natural`` (written by another tool
or a later runner) is read the same way (:data:`SESSION_PHASES`); which display a pattern lights is read from the session's ``[patterns]`` table
(:func:`opacityhull.acquire.patterns.natural_domain`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np

from ..errors import FormatError, InputError
from ..riggeometry import view_id

log = logging.getLogger(__name__)

__all__ = [
    "natural_shots",
    "estimate_view_natural",
    "estimate_session_natural",
    "natural_mask",
    "SESSION_PHASE",
    "SESSION_PHASES",
    "has_natural_phase",
]

#: the session phase the capture runner records the natural images under
SESSION_PHASE = "envmatte"
#: every session phase name that holds natural images (both are in :data:`opacityhull.session.PHASES`)
SESSION_PHASES = ("envmatte", "natural")


def has_natural_phase(session) -> bool:
    """True if the session holds natural-illumination images under either phase name."""
    return any(p in session.phases() for p in SESSION_PHASES)


def natural_shots(session, camera: int, table_deg: float) -> dict[str, list[tuple[int, str]]]:
    """``{display: [(pattern id, shot key), ...]}`` of one view's natural shots, by
    pattern id. Shots whose pattern lights several displays at once (an older envmatte
    capture) cannot be split into domains and are skipped (logged)."""
    from ..acquire.patterns import natural_domain

    out: dict[str, list[tuple[int, str]]] = {}
    seen: set[str] = set()
    skipped = 0
    cache = getattr(session, "_natural_domain_cache", None)
    if cache is None:
        cache = {}
        try:
            session._natural_domain_cache = cache
        except AttributeError:  # pragma: no cover - a frozen session object
            log.debug("%s: session object takes no cache; display domains are re-read per view", session.root)
    recs = [r for ph in SESSION_PHASES for r in session.select(phase=ph, camera=camera, table_deg=table_deg, kind=None)]
    for r in recs:
        if r.pattern is None or not r.object_present or r.shot in seen:
            continue
        seen.add(r.shot)
        pid = int(r.pattern)
        if pid not in cache:
            cache[pid] = natural_domain(session, pid)
        d = cache[pid]
        if d is None:
            skipped += 1
            continue
        out.setdefault(d, []).append((pid, r.shot))
    if skipped:
        log.warning(
            "%s: %d natural shot(s) of view %s light several displays at once; not used",
            session.root,
            skipped,
            view_id(camera, table_deg),
        )
    return {d: sorted(v) for d, v in out.items()}


def estimate_view_natural(
    session,
    shots: Sequence[tuple[int, str]],
    display: str,
    mask: np.ndarray,
    *,
    n_kernels: int = 25,
    rel_tol: float = 1e-8,
):
    """One view and display: the field of the pixels where ``mask`` (H, W) is True.

    Returns a :class:`~opacityhull.reconstruct.natural.NaturalField` with ``pixel_index``.
    """
    from .natural import NaturalConfig, estimate_natural

    spec = session.geometry.display(display)
    mask = np.asarray(mask, bool)
    idx = np.flatnonzero(mask.reshape(-1))
    L = np.stack([session.pattern_image(display, pid)[..., :3].astype(np.float64) for pid, _ in shots])
    L *= float(spec.max_radiance)
    B = np.empty((len(shots), idx.size, 3))
    for j, (_, shot) in enumerate(shots):
        img = np.asarray(session.load_radiance(shot), np.float64)
        if img.shape[:2] != mask.shape:
            raise FormatError(
                f"{session.root}: shot {shot} is {img.shape[1]}x{img.shape[0]}, the matte "
                f"{mask.shape[1]}x{mask.shape[0]}"
            )
        B[j] = img.reshape(-1, img.shape[2])[idx, :3]
    # A sensor's non-finite pixel (never expected from load_radiance) must not poison the solve.
    B = np.nan_to_num(B, nan=0.0, posinf=0.0, neginf=0.0)
    field = estimate_natural(L, B, config=NaturalConfig(n_kernels=n_kernels, rel_tol=rel_tol))
    return dataclasses.replace(field, pixel_index=idx.astype(np.int32), image_hw=tuple(mask.shape))


def natural_mask(
    alpha: np.ndarray, *, alpha_min: float = 0.5, alpha_low: float | None = 0.1, fill_holes: bool = True
) -> np.ndarray:
    """The pixels of one view that get a field: bool (H, W).

    α > ``alpha_min``, grown into the connected pixels with α > ``alpha_low``, with, by
    default, its enclosed holes filled. A clear glass passes the backdrop through
    (refracted), so two-backdrop matting gives it a low α inside its rim — and those are
    exactly the pixels the display field is for. Where that low-α glass reaches the
    outline (a neck or a shoulder seen edge-on) it is not enclosed, so filling alone
    misses it: on the simulated glass (``builtin:natural``, 4 views) α > 0.5 filled left
    2–202 of 1,745–1,864 truly covered pixels without a field, and those carried 27–100 %
    of the display half's error (0.52 against 0.04 inside the field on one view). Grown
    through α > 0.1 it misses none and adds 4–29 pixels the object does not cover
    (its matte's halo). A gap open to the background (a handle's hole seen through,
    α ≈ 0) and isolated matte noise on the backdrop (not connected) stay out.
    ``alpha_low=None`` (or ≥ ``alpha_min``) does not grow."""
    from scipy import ndimage as ndi

    a = np.asarray(alpha, np.float64)
    m = a > alpha_min
    if alpha_low is not None and alpha_low < alpha_min and m.any():
        low = a > alpha_low
        lab, _ = cast("tuple[np.ndarray, int]", ndi.label(low))
        keep = np.unique(lab[m & low])
        m = m | np.isin(lab, keep[keep > 0])
    return np.asarray(ndi.binary_fill_holes(m), bool) if fill_holes else m


def estimate_session_natural(
    session,
    views: Sequence[tuple[int, float]],
    view_cameras,
    alphas: Sequence[np.ndarray],
    out_dir,
    *,
    n_kernels: int = 25,
    alpha_min: float = 0.5,
    alpha_low: float | None = 0.1,
    fill_holes: bool = True,
    rel_tol: float = 1e-8,
    weights_dtype: str = "float16",
    progress: Callable[[int, int], None] | None = None,
) -> dict:
    """Estimate and write the natural-illumination field of every view and display.

    Parameters
    ----------
    session : Session
    views : [(camera index, table_deg)], the model's views, in model order.
    view_cameras : the views' cameras (recorded only for consistency checks of size).
    alphas : per view float (H, W) matte; pixels with α > ``alpha_min``, grown through
        the connected pixels with α > ``alpha_low``, and the holes that region encloses
        (``fill_holes``, :func:`natural_mask`), are estimated.
        The photographs are the whole radiance reaching the camera, the backdrop seen
        past the object included; where α is small outside the object that backdrop is
        all there is, and relit it would add the environment itself to the view's
        premultiplied colour (matte noise on the backdrop showed as a grid of
        environment pixels). So only the object proper (default α > 0.5, holes filled:
        a glass's low-α interior) gets a field; its fringe keeps the light-array part
        only.
    out_dir : path, the model folder; fields go to ``natural/<view_id>/<display>.npz``.
    n_kernels : K (default 25, the paper's); a view/display with fewer images is an error.
    weights_dtype : "float16" (the stored size, 355 B/px at K = 25) or "float32".
    progress : callable(done, total) over (view, display) pairs.

    Returns
    -------
    dict: ``present``, ``displays`` {name: {"domain_hw": [H_d, W_d], "images": N}},
    ``n_kernels``, ``pixels``, ``kernels_mean``, ``residual_median``/``_p95``,
    ``bytes``, ``seconds``, ``pixels_per_s``, ``files``.

    Raises
    ------
    InputError
        The session has no natural phase, a view has none of its shots, or N < K.
    """
    from .natural import field_path, save_field

    t0 = time.perf_counter()
    views = list(views)
    if len(alphas) != len(views) or (view_cameras is not None and len(view_cameras) != len(views)):
        raise InputError(
            f"estimate_session_natural: {len(views)} views, {len(alphas)} mattes, "
            f"{None if view_cameras is None else len(view_cameras)} cameras: they must match"
        )
    if not has_natural_phase(session):
        raise InputError(
            f"{session.root}: the session has no natural-illumination phase (no "
            f"{' or '.join(repr(p) for p in SESSION_PHASES)} images); capture it with a plan that has "
            "[phases.natural]"
        )
    per_view = [natural_shots(session, c, a) for c, a in views]
    displays = sorted({d for pv in per_view for d in pv})
    if not displays:
        raise InputError(
            f"{session.root}: no natural shot lights a single display (an older envmatte capture "
            "showing one image on every display cannot be split into illumination domains)"
        )
    for (c, a), pv in zip(views, per_view, strict=True):
        missing = [d for d in displays if d not in pv]
        if missing:
            raise InputError(f"{session.root}: view {view_id(c, a)} has no natural shots on display(s) {missing}")
        for d, shots in pv.items():
            if len(shots) < n_kernels:
                raise InputError(
                    f"{session.root}: view {view_id(c, a)}, display {d!r}: {len(shots)} natural "
                    f"images but n_kernels={n_kernels}; the estimate needs N >= K"
                )
    out_dir = Path(out_dir)
    total = len(views) * len(displays)
    done = 0
    pixels, nbytes, kern, res, files = 0, 0, [], [], []
    info = {}
    for i, ((c, a), pv) in enumerate(zip(views, per_view, strict=True)):
        vid = view_id(c, a)
        mask = natural_mask(alphas[i], alpha_min=alpha_min, alpha_low=alpha_low, fill_holes=fill_holes)
        for d in displays:
            f = estimate_view_natural(session, pv[d], d, mask, n_kernels=n_kernels, rel_tol=rel_tol)
            f = dataclasses.replace(
                f,
                meta={
                    "view_id": vid,
                    "display": d,
                    "n_kernels": n_kernels,
                    "alpha_min": alpha_min,
                    "alpha_low": alpha_low,
                    "fill_holes": fill_holes,
                    "rel_tol": rel_tol,
                    "patterns": [p for p, _ in pv[d]],
                    "session": str(session.root),
                },
            )
            path = save_field(field_path(out_dir, vid, d), f, weights_dtype=weights_dtype)
            files.append(str(path.relative_to(out_dir)))
            nbytes += path.stat().st_size
            pixels += f.n_pixels
            kern.append(f.n_kernels.astype(np.float64))
            res.append(f.residual.astype(np.float64))
            info.setdefault(d, {"domain_hw": list(f.domain_hw), "images": f.n_images})
            done += 1
            if progress:
                progress(done, total)
            log.info("natural %s/%s: %d px, %d images", vid, d, f.n_pixels, f.n_images)
    secs = time.perf_counter() - t0
    k_all = np.concatenate(kern) if kern else np.zeros(0)
    r_all = np.concatenate(res) if res else np.zeros(0)
    return {
        "present": True,
        "displays": info,
        "n_kernels": int(n_kernels),
        "weights_dtype": weights_dtype,
        "pixels": int(pixels),
        "kernels_mean": float(k_all.mean()) if k_all.size else 0.0,
        "residual_median": float(np.median(r_all)) if r_all.size else 0.0,
        "residual_p95": float(np.percentile(r_all, 95)) if r_all.size else 0.0,
        "bytes": int(nbytes),
        "seconds": secs,
        "pixels_per_s": pixels / max(secs, 1e-9),
        "files": files,
    }
