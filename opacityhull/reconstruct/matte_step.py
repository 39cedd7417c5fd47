"""The matting step of one view, on its own so the per-view workers
(:mod:`.perview`) and :mod:`.build` share it without importing each other: the
matting images of a view (object and backdrop shots, or backdrops predicted from the
display geometry), imported masks, the solve, and the build's per-view matte cache
(``.npy`` + sidecar ``.json``, see :func:`store_matte`)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import FormatError, InputError
from ..riggeometry import view_id
from ..session import Session, check_finite
from .matting import MattingOptions, backdrop_from_displays, solve_matte

log = logging.getLogger(__name__)


def _jsonable(d):
    from ..jsonio import to_jsonable

    return to_jsonable(d)


def _rgb(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img, dtype=np.float32)
    if img.shape[2] == 1 or img.shape[2] == 2:
        return np.repeat(img[..., :1], 3, axis=2)
    return img[..., :3]


def _rgb_clip(session: Session, shot: str) -> tuple[np.ndarray, float]:
    """(H, W, 3) radiance of a shot and its clip level (:meth:`Session.load_radiance_clip`)."""
    img, clip = session.load_radiance_clip(shot)
    return _rgb(img), clip


def load_matting_pairs(
    session: Session, camera: int, table_deg: float, view_cam: Camera | None = None, *, backdrops: str = "auto"
):
    """(C, B, c_clip, b_clip, source) of one view: observations (K, H, W, 3), backdrops,
    clip levels (K,), and where the backdrops came from.

    ``backdrops``: "auto" (object-absent captures when at least two patterns have them,
    else the display geometry), "object-absent" (error without them) or "geometry"
    (predict them even when captures exist: for comparisons)."""
    recs = session.select(phase="matting", camera=camera, table_deg=table_deg, kind=None)
    with_obj: dict = {}
    without: dict = {}
    for r in recs:
        (with_obj if r.object_present else without).setdefault(r.pattern, r.shot)
    if not with_obj:
        raise FormatError(f"{session.root}: no matting images of view {view_id(camera, table_deg)}")
    C, B, cc, bc = [], [], [], []
    paired = [p for p in sorted(with_obj, key=lambda x: -1 if x is None else x) if p in without]
    if backdrops == "object-absent" and len(paired) < 2:
        raise FormatError(
            f"{session.root}: view {view_id(camera, table_deg)} has {len(paired)} backdrop pattern(s) "
            "shot with the object absent; triangulation matting needs at least 2"
        )
    if len(paired) >= 2 and backdrops != "geometry":
        for p in paired:
            c_img, c_clip = _rgb_clip(session, with_obj[p])
            b_img, b_clip = _rgb_clip(session, without[p])
            C.append(c_img)
            B.append(b_img)
            cc.append(c_clip)
            bc.append(b_clip)
        source = "object-absent captures"
    else:
        if view_cam is None:
            raise InputError("backdrops from display geometry need the view's camera")
        geo = session.geometry
        if not geo.displays:
            raise FormatError(
                f"{session.root}: view {view_id(camera, table_deg)} has no object-absent backdrop "
                "shots and the rig has no displays to predict them from; object-absent backdrops "
                "are required"
            )
        for p in sorted(with_obj, key=lambda x: -1 if x is None else x):
            c_img, c_clip = _rgb_clip(session, with_obj[p])
            pats = {}
            if p is not None:
                for d in geo.displays:
                    f = session.root / "patterns" / d.name / f"p{int(p):03d}.png"
                    if f.is_file():
                        pats[d.name] = session.pattern_image(d.name, p)
            cam = view_cam
            if (cam.width, cam.height) != (c_img.shape[1], c_img.shape[0]):
                raise FormatError(
                    f"view {view_id(camera, table_deg)}: image is {c_img.shape[1]}x{c_img.shape[0]}, "
                    f"camera is {cam.width}x{cam.height}"
                )
            B.append(backdrop_from_displays(cam, table_deg, geo, pats))
            C.append(c_img)
            cc.append(c_clip)
            bc.append(float("inf"))
        source = "display geometry" + (" (no object-absent captures)" if backdrops == "auto" else " (requested)")
    shapes = {x.shape for x in C + B}
    if len(shapes) != 1:
        raise FormatError(f"view {view_id(camera, table_deg)}: matting images differ in size {sorted(shapes)}")
    return np.stack(C), np.stack(B), np.array(cc, np.float32), np.array(bc, np.float32), source


def _mask_alpha(session: Session, camera: int, table_deg: float) -> np.ndarray:
    recs = session.select(phase="mask", camera=camera, table_deg=table_deg, kind=None)
    if not recs:
        raise FormatError(f"{session.root}: no mask image of view {view_id(camera, table_deg)}")
    m = session.load_image(recs[-1])
    a = m[..., 3] if m.shape[2] == 4 else m[..., 0]
    return np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0).astype(np.float32)


def _replace_unsynced(path: Path, data: bytes) -> None:
    """``data`` to ``path`` through a temporary file and a rename, without fsync: a killed
    process leaves the old file or the new one, never half of one. For the build's
    per-view cache only (an fsync per view cost more than the matting on a loaded
    disk); after a power loss the content hash in the sidecar catches a torn file."""
    import os
    import threading

    from ..errors import write_error

    tmp = path.with_name(f".tmp-{os.getpid()}-{threading.get_ident():x}-{path.name}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise (write_error(e, path) or e) from None


def store_matte(alpha_path: Path, alpha: np.ndarray, meta: dict) -> dict:
    """Write one view's alpha (``.npy``, float32, exact) and then its sidecar ``.json``
    (``meta`` with the step key, the alpha's SHA-256 and shape): the sidecar is the mark
    of a finished view, so a view killed between the two is redone. Returns the
    sidecar's content."""
    import hashlib
    import io

    alpha_path = Path(alpha_path)
    a = np.ascontiguousarray(alpha, np.float32)
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    _replace_unsynced(alpha_path, buf.getvalue())
    out: dict = {**meta, "sha256": hashlib.sha256(a.tobytes()).hexdigest(), "shape": list(a.shape)}
    text = json.dumps(_jsonable(out))
    _replace_unsynced(alpha_path.with_suffix(".json"), (text + "\n").encode())
    return json.loads(text)  # what a resumed build reads back, so both paths see the same


def _stored_matte(alpha_path: Path, key: str, shape: tuple[int, int]) -> tuple[np.ndarray, dict] | None:
    """The alpha and sidecar of a view matted before with the same key, or None (no
    sidecar, another key, or a file whose bytes no longer match its hash)."""
    import hashlib

    try:
        meta = json.loads(alpha_path.with_suffix(".json").read_text())
        if not isinstance(meta, dict) or meta.get("key") != key:
            return None
        a = np.load(alpha_path, allow_pickle=False)
    except (OSError, ValueError, EOFError):
        return None
    if (
        a.dtype != np.float32
        or a.shape != tuple(shape)
        or hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() != meta.get("sha256")
    ):
        log.warning("%s: does not match its sidecar; the view is matted again", alpha_path)
        return None
    return a, meta


def _load_matte(alpha_path: Path, shape: tuple[int, int]) -> np.ndarray:
    try:
        a = np.load(alpha_path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise FormatError(f"{alpha_path}: unreadable matte ({e}); build again without --resume") from None
    if a.shape != shape or a.dtype != np.float32:
        raise FormatError(f"{alpha_path}: matte is {a.dtype} {a.shape}, expected float32 {shape}")
    return a


def matte_for_build(
    session: Session,
    camera: int,
    table_deg: float,
    view_cam: Camera,
    *,
    use_masks: bool,
    backdrops: str,
    matting: MattingOptions,
) -> tuple[np.ndarray, dict]:
    """The matting step of one view: (alpha (H, W) float32, meta) where meta has the
    backdrop ``source``, the matting ``stats`` (None for imported masks) and
    ``nonfinite`` (notes on NaN/Inf input pixels)."""
    vid = view_id(camera, table_deg)
    nonfinite: list[str] = []
    stats = None
    if use_masks:
        alpha = _mask_alpha(session, camera, table_deg)
        src = "imported masks"
    else:
        C, B, cc, bc, src = load_matting_pairs(session, camera, table_deg, view_cam, backdrops=backdrops)
        for img, where in ((C, f"view {vid} matting shots"), (B, f"view {vid} backdrop shots")):
            n = check_finite(img, where=where)
            if n:
                nonfinite.append(n)
        res = solve_matte(C, B, c_saturation=cc, b_saturation=bc, options=matting)
        alpha = res.alpha
        stats = {
            "view": vid,
            "unknown_frac": float(res.unknown.mean()),
            "saturated_frac": float(res.saturated.mean()),
            "invalid_frac": float(res.invalid.mean()),
            "noise_sigma": res.noise_sigma,
            "K": int(C.shape[0]),
            "drift": res.drift.to_dict() if res.drift is not None else None,
        }
    if alpha.shape != (view_cam.height, view_cam.width):
        raise FormatError(
            f"view {vid}: alpha is {alpha.shape[1]}x{alpha.shape[0]}, camera is {view_cam.width}x{view_cam.height}"
        )
    from .liveviews import LIVE_VIEWS

    alpha = LIVE_VIEWS.track(vid, np.ascontiguousarray(alpha, np.float32))
    return alpha, {"view": vid, "source": src, "stats": stats, "nonfinite": nonfinite}
