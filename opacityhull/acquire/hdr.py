"""Exposure brackets → linear radiance (a separate step over a session; raw brackets stay).

* Linear sensors (``CameraInfo.linear``): a weighted average of ``v_k / (gain * t_k)``
  with weight ``w_k = hat(x_k) * t_k`` — the hat ``1 - |2x - 1|`` of the pixel's
  normalised value ``x = max_c v / white`` down-weights the noisy dark end, and the
  factor ``t_k`` is the inverse variance of a shot-noise-limited estimate. A sample
  with any channel at or above ``saturation * white`` gets zero weight (it is clipped);
  the weight is per pixel, not per channel, so a clipped channel cannot tilt the hue.
  Pixels saturated in every exposure take the shortest exposure (a lower bound) and are
  counted and flagged; pixels too dark for any weight take the longest exposure.
* Non-linear sensors (8-bit, unknown response): Debevec & Malik (1997) response
  recovery with OpenCV (``CalibrateDebevec`` over a mosaic of several shots' brackets,
  so that one response per camera is fitted from many scenes), then ``MergeDebevec``.
  The result is relative radiance (OpenCV normalises the response to 1 at code 128),
  divided by the camera gain.

Merges are appended to the manifest as ``kind = "hdr"`` records with ``sources`` (the
bracket ids) at ``images/<shot>_hdr.exr``; :meth:`Session.load_radiance` prefers them.
"""

from __future__ import annotations

from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import FormatError, InputError, ShapeError
from ..session import Session, SessionWriter, ShotRecord, sha256_file

__all__ = ["merge_linear", "merge_linear_reference", "recover_response", "merge_debevec", "hdr_session"]


def _stack(images, exposures_s) -> tuple[np.ndarray, np.ndarray]:
    if len(images) == 0 or len(images) != len(exposures_s):
        raise InputError(f"{len(images)} images for {len(exposures_s)} exposure times")
    imgs = [np.asarray(im, dtype=np.float32) for im in images]
    shape = imgs[0].shape
    if len(shape) != 3:
        raise ShapeError(f"bracket images must be (H, W, C), got {shape}")
    for im in imgs:
        if im.shape != shape:
            raise ShapeError(f"bracket images differ in shape: {im.shape} vs {shape}")
    t = np.asarray(exposures_s, dtype=np.float64)
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise InputError(f"exposure times must be positive, got {list(exposures_s)}")
    return np.stack(imgs), t


def merge_linear(
    images: Sequence[np.ndarray],
    exposures_s: Sequence[float],
    *,
    white_level: float = 1.0,
    saturation: float = 0.98,
    gain: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Merge a bracket of linear images into radiance.

    Parameters
    ----------
    images : sequence of (H, W, C) float arrays, sensor values ``gain * t * L`` clipped at
        ``white_level``.
    exposures_s : exposure time of each image (s).
    white_level : sensor value at saturation.
    saturation : fraction of ``white_level`` from which a sample counts as clipped.
    gain : sensor value per (radiance × second).

    Returns
    -------
    radiance : (H, W, C) float32
    all_saturated : (H, W) bool — clipped in every exposure (value is a lower bound).
    """
    v, t = _stack(images, exposures_s)
    white = float(white_level)
    x = np.max(v, axis=-1) / white  # (K, H, W)
    sat = x >= saturation
    w = (1.0 - np.abs(2.0 * np.clip(x, 0.0, 1.0) - 1.0)) * t[:, None, None]
    w = np.where(sat, 0.0, w)
    est = v / (gain * t)[:, None, None, None]
    wsum = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        L = (w[..., None] * est).sum(axis=0) / wsum[..., None]
    order = np.argsort(t)
    shortest, longest = order[0], order[-1]
    all_sat = np.all(sat, axis=0)
    # no weight: clipped everywhere -> shortest; too dark everywhere -> longest unclipped
    nz = wsum <= 0
    if np.any(nz):
        unsat_longest = np.full(x.shape[1:], -1, dtype=np.int64)
        for k in order:  # ascending t: the last unsaturated wins
            unsat_longest = np.where(~sat[k], k, unsat_longest)
        pick = np.where(all_sat, shortest, np.where(unsat_longest >= 0, unsat_longest, longest))
        fallback = np.take_along_axis(est, pick[None, ..., None].repeat(est.shape[-1], axis=-1), axis=0)[0]
        L = np.where(nz[..., None], fallback, L)
    return L.astype(np.float32), all_sat


def merge_linear_reference(images, exposures_s, *, white_level=1.0, saturation=0.98, gain=1.0):
    """Slow per-pixel loop implementing the same rule as :func:`merge_linear` (test oracle)."""
    v, t = _stack(images, exposures_s)
    K, H, W, C = v.shape
    out = np.zeros((H, W, C), np.float64)
    flag = np.zeros((H, W), bool)
    for i in range(H):
        for j in range(W):
            num, den = np.zeros(C), 0.0
            unsat = []
            for k in range(K):
                x = max(v[k, i, j]) / white_level
                if x >= saturation:
                    continue
                unsat.append(k)
                wk = (1 - abs(2 * min(max(x, 0.0), 1.0) - 1)) * t[k]
                num += wk * v[k, i, j] / (gain * t[k])
                den += wk
            if den > 0:
                out[i, j] = num / den
            elif not unsat:
                k = int(np.argmin(t))
                out[i, j] = v[k, i, j] / (gain * t[k])
                flag[i, j] = True
            else:
                k = max(unsat, key=lambda q: t[q])
                out[i, j] = v[k, i, j] / (gain * t[k])
    return out.astype(np.float32), flag


def _to_u8(img: np.ndarray, white_level: float) -> np.ndarray:
    return np.clip(np.round(np.asarray(img, np.float32)[..., :3] / white_level * 255.0), 0, 255).astype(np.uint8)


def recover_response(
    brackets: Sequence[Sequence[np.ndarray]],
    exposures_s: Sequence[float],
    *,
    white_level: float = 1.0,
    samples: int = 70,
    lambda_smooth: float = 10.0,
    seed: int = 0,
) -> np.ndarray:
    """Debevec–Malik camera response from brackets of one or more scenes.

    Parameters
    ----------
    brackets : list of brackets; each a list of (H, W, 3) images (values in
        [0, white_level], one per exposure, same order as ``exposures_s``). All scenes
        are tiled side by side so one response is fitted from all of them.
    exposures_s : exposure times (s).

    Returns
    -------
    (256, 3) float32: relative exposure (radiance × time) per 8-bit code and channel.
    """
    import cv2

    if not brackets:
        raise InputError("no brackets to recover a response from")
    rows = []
    for b in brackets:
        if len(b) != len(exposures_s):
            raise InputError(f"a bracket has {len(b)} images for {len(exposures_s)} exposure times")
        rows.append([_to_u8(im, white_level) for im in b])
    h = min(r[0].shape[0] for r in rows)
    mosaic = [np.ascontiguousarray(np.concatenate([r[k][:h] for r in rows], axis=1)) for k in range(len(exposures_s))]
    cv2.setRNGSeed(int(seed))
    cal = cv2.createCalibrateDebevec(samples=int(samples), lambda_=float(lambda_smooth), random=False)
    resp = cal.process(mosaic, np.asarray(exposures_s, dtype=np.float32))
    return np.asarray(resp, np.float32).reshape(256, 3)


def merge_debevec(
    images: Sequence[np.ndarray],
    exposures_s: Sequence[float],
    response: np.ndarray,
    *,
    white_level: float = 1.0,
    gain: float = 1.0,
) -> np.ndarray:
    """Merge a bracket of non-linear 8-bit-coded images with a recovered response.

    Returns relative radiance (H, W, 3) float32 (divided by ``gain``)."""
    import cv2

    u8 = [np.ascontiguousarray(_to_u8(im, white_level)) for im in images]
    resp = np.asarray(response, np.float32).reshape(256, 1, 3)
    hdr = cv2.createMergeDebevec().process(u8, np.asarray(exposures_s, dtype=np.float32), resp)
    return (np.asarray(hdr, np.float32) / np.float32(gain)).astype(np.float32)


# --------------------------------------------------------------------------- sessions


def _brackets(sess: Session, phases) -> dict[str, list[ShotRecord]]:
    out: dict[str, list[ShotRecord]] = {}
    for r in sess.records:
        if r.kind != "raw" or r.exposure_s is None or (phases and r.phase not in phases):
            continue
        out.setdefault(r.shot, []).append(r)
    return {k: sorted(v, key=_exposure_s) for k, v in out.items() if len(v) >= 2}


def _exposure_s(r: ShotRecord) -> float:
    """A raw record's exposure; :func:`_brackets` keeps only records that have one."""
    if r.exposure_s is None:
        raise FormatError(f"record {r.id}: raw image without exposure_s")
    return float(r.exposure_s)


def hdr_session(
    root,
    *,
    phases: Sequence[str] | None = None,
    method: str = "auto",
    saturation: float = 0.98,
    force: bool = False,
    progress: Callable[[int, int], None] | None = None,
    response_shots: int = 8,
) -> dict:
    """Merge every bracketed shot of a session and append ``kind = "hdr"`` records.

    Parameters
    ----------
    root : session folder.
    phases : restrict to these phases (default all).
    method : ``"auto"`` (per camera: linear merge if the camera reported a linear
        sensor, Debevec otherwise), ``"linear"`` or ``"debevec"``.
    saturation : clipped-sample threshold as a fraction of the white level.
    force : merge again even when an up-to-date merge is listed.
    response_shots : how many shots per camera feed the Debevec response recovery.

    Returns
    -------
    dict: ``merged``, ``skipped`` (up to date), ``shots`` (bracketed shots),
    ``saturated_px`` (pixels clipped in every exposure, summed), ``methods`` per camera,
    ``responses`` (files of recovered responses).
    """
    if method not in ("auto", "linear", "debevec"):
        raise InputError(f"--method must be auto, linear or debevec, got {method!r}")
    if not 0 < saturation <= 1:
        raise InputError(f"--saturation must be in (0, 1], got {saturation}")
    root = Path(root)
    sess = Session.open(root)
    if phases:
        from ..session import PHASES, phase_names

        unknown = [p for p in phases if p not in PHASES]
        if unknown:
            raise InputError(f"--phase {unknown[0]!r}: not a phase; expected one of {', '.join(PHASES)}")
        have = set(sess.phases())
        absent = [p for p in phases if not phase_names([p]) & have]
        if absent:
            raise InputError(
                f"--phase {absent[0]!r}: {root} has no images of that phase (it has "
                f"{', '.join(sorted(have)) or 'none'})"
            )
    groups = _brackets(sess, phase_names(phases) if phases else None)
    white = sess.white_level
    linear_of = {int(c.get("index", i)): bool(c.get("linear", True)) for i, c in enumerate(sess.camera_info)}
    existing = {r.shot: r for r in sess.records if r.kind == "hdr"}
    cams = sorted({recs[0].camera for recs in groups.values()})
    methods = {c: (("linear" if linear_of.get(c, True) else "debevec") if method == "auto" else method) for c in cams}
    responses: dict[int, np.ndarray] = {}
    resp_files = {}
    geom_gain = {c: sess.gain(c) for c in cams}  # a corrupt [rig] table is a FormatError, not gain 1

    def up_to_date(shot, recs) -> bool:
        h = existing.get(shot)
        if h is None or tuple(h.sources) != tuple(r.id for r in recs):
            return False
        if h.extra.get("sources_sha256") != [r.sha256 for r in recs]:  # a bracket was re-shot since
            return False
        p = root / h.path
        return p.is_file() and sha256_file(p) == h.sha256

    todo = [(s, recs) for s, recs in sorted(groups.items()) if force or not up_to_date(s, recs)]
    for c in cams:
        if methods[c] != "debevec" or not any(recs[0].camera == c for _, recs in todo):
            continue
        cand = [recs for _, recs in sorted(groups.items()) if recs[0].camera == c]
        times = [_exposure_s(r) for r in cand[0]]
        cand = [recs for recs in cand if [_exposure_s(r) for r in recs] == times]
        step = max(1, len(cand) // response_shots)
        chosen = cand[::step][:response_shots]
        responses[c] = recover_response(
            [[sess.load_image(r) for r in recs] for recs in chosen], times, white_level=white
        )
        from ..imageio import atomic_path

        rp = root / "hdr" / f"response_c{c}.csv"
        with atomic_path(rp) as tmp:
            np.savetxt(tmp, responses[c], delimiter=",", header="code-indexed relative exposure, columns R,G,B")
        resp_files[c] = rp.relative_to(root).as_posix()

    merged = 0
    sat_px = 0
    with SessionWriter(root).resume() as w:
        for k, (shot, recs) in enumerate(todo):
            imgs = [sess.load_image(r)[..., :3] for r in recs]
            times = [_exposure_s(r) for r in recs]
            c = recs[0].camera
            extra = {"method": methods[c], "saturation": saturation, "sources_sha256": [r.sha256 for r in recs]}
            if methods[c] == "linear":
                L, flag = merge_linear(imgs, times, white_level=white, saturation=saturation, gain=geom_gain[c])
                n = int(flag.sum())
                extra["saturated_px"] = n
                sat_px += n
            else:
                L = merge_debevec(imgs, times, responses[c], white_level=white, gain=geom_gain[c])
                extra["response"] = resp_files.get(c, "")
            r0 = recs[0]
            w.add_image(
                L,
                id=f"{shot}/hdr",
                shot=shot,
                phase=r0.phase,
                camera=c,
                table_deg=r0.table_deg,
                rel_path=f"images/{shot}_hdr.exr",
                kind="hdr",
                sources=tuple(r.id for r in recs),
                lights_deg=r0.lights_deg,
                light=r0.light,
                pattern=r0.pattern,
                object_present=r0.object_present,
                extra=extra,
                replace=shot in existing,
            )
            merged += 1
            if progress is not None:
                progress(k + 1, len(todo))
    return {
        "session": str(root),
        "shots": len(groups),
        "merged": merged,
        "skipped": len(groups) - len(todo),
        "saturated_px": sat_px,
        "methods": {str(c): m for c, m in methods.items()},
        "responses": {str(c): f for c, f in resp_files.items()},
    }
