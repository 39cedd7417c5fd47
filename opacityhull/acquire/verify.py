"""Check a session folder against its manifest, and summarise it.

``verify_session``: every listed image exists with its size and sha256, no file under
``images/`` is unlisted, and — for captured sessions — how many images each phase has
against what the plan asks for.
"""

from __future__ import annotations

from pathlib import Path
from collections.abc import Callable

from ..errors import ConfigError, FormatError
from ..session import Session, read_manifest, sha256_file

__all__ = ["verify_session", "session_info", "planned_counts"]


def planned_counts(sess: Session) -> dict[str, int] | None:
    """Images per phase the session's plan asks for, or None (imported sessions)."""
    from .plan import parse_plan
    from .schedule import expected_counts, schedule

    if not sess.plan or "phases" not in sess.plan:
        return None
    try:
        plan = parse_plan(sess.plan, where=f"{sess.root / 'session.toml'}:plan")
        return expected_counts(schedule(plan, sess.geometry))
    except (ConfigError, FormatError):
        return None


def verify_session(root, *, progress: Callable[[int, int], None] | None = None, hash_files: bool = True) -> dict:
    """Verify a session folder.

    Returns
    -------
    dict with ``ok`` (no missing, corrupt or unlisted file, every record valid),
    ``invalid`` (messages naming each manifest line that does not parse as the session
    format, and a bad ``white_level``), ``images`` (listed images,
    the last record of an id counting), ``missing``, ``corrupt``, ``unlisted`` (lists of
    paths relative to the session), ``per_phase`` (raw images listed per phase),
    ``planned_per_phase`` and ``complete`` (the plan's counts are all there; None for
    sessions without a capture plan), ``superseded`` (records replaced by a re-shoot)
    and ``hdr`` (HDR merges listed).
    """
    root = Path(root)
    # every record must parse as the session format (a "table_deg": "ninety" would
    # otherwise pass here and break build): read leniently, report each bad line
    meta = Session.open_meta(root)
    invalid: list[str] = []
    sess = Session(root, meta, list(read_manifest(root / "manifest.jsonl", problems=invalid)))
    try:
        _ = sess.white_level  # the property validates
    except FormatError as e:
        invalid.append(str(e))
    missing, corrupt = [], []
    listed: set[str] = set()
    recs = sess.records
    for k, r in enumerate(recs):
        listed.add(r.path)
        p = root / r.path
        if not p.is_file():
            missing.append(r.path)
        elif p.stat().st_size != r.bytes or (hash_files and sha256_file(p) != r.sha256):
            corrupt.append(r.path)
        if progress is not None:
            progress(k + 1, len(recs))
    # a superseded record's path is the same file as its replacement's; nothing else to list
    unlisted = []
    img_dir = root / "images"
    if img_dir.is_dir():
        for p in sorted(img_dir.rglob("*")):
            if p.is_file():
                rel = p.relative_to(root).as_posix()
                if rel not in listed:
                    unlisted.append(rel)
    per_phase: dict[str, int] = {}
    for r in recs:
        if r.kind == "raw":
            per_phase[r.phase] = per_phase.get(r.phase, 0) + 1
    planned = planned_counts(sess)
    complete = None
    if planned is not None:
        complete = all(per_phase.get(p, 0) == n for p, n in planned.items()) and set(per_phase) <= set(planned)
    ok = not missing and not corrupt and not unlisted and not invalid
    return {
        "ok": ok,
        "invalid": invalid,
        "images": sum(1 for r in recs if r.kind == "raw"),
        "missing": missing,
        "corrupt": corrupt,
        "unlisted": unlisted,
        "per_phase": per_phase,
        "planned_per_phase": planned,
        "complete": complete,
        "superseded": sess.superseded,
        "hdr": sum(1 for r in recs if r.kind == "hdr"),
        "session": str(root),
    }


def session_info(root) -> dict:
    """Phases, views, counts and bytes of a session (reads only the manifest and session.toml)."""
    root = Path(root)
    sess = Session.open(root)
    phases: dict[str, dict] = {}
    for r in sess.records:
        ph = phases.setdefault(
            r.phase,
            {
                "images": 0,
                "hdr": 0,
                "bytes": 0,
                "views": set(),
                "exposures_s": set(),
                "cameras": set(),
                "table_deg": set(),
            },
        )
        ph["hdr" if r.kind == "hdr" else "images"] += 1
        ph["bytes"] += int(r.bytes)
        ph["views"].add(r.view)
        ph["cameras"].add(r.camera)
        ph["table_deg"].add(round(r.table_deg, 6))
        if r.exposure_s is not None:
            ph["exposures_s"].add(r.exposure_s)
    out_phases = {}
    for name, ph in phases.items():
        out_phases[name] = {
            "images": ph["images"],
            "hdr": ph["hdr"],
            "bytes": ph["bytes"],
            "views": len(ph["views"]),
            "cameras": sorted(ph["cameras"]),
            "table_deg": sorted(ph["table_deg"]),
            "exposures_s": sorted(ph["exposures_s"]),
        }
    try:
        geom = sess.geometry
        rig = {
            "cameras": [c.name for c in geom.cameras],
            "lights": [L.id for L in geom.lights],
            "displays": [d.name for d in geom.displays],
        }
    except (FormatError, ConfigError) as e:
        rig = {"error": str(e)}
    s = sess.meta.get("session", {})
    return {
        "session": str(root),
        "format": s.get("format"),
        "software_version": s.get("software_version"),
        "created_utc": s.get("created_utc"),
        "rig_source": s.get("rig_source", ""),
        "plan": sess.plan.get("plan", {}).get("name", s.get("plan_name", "")),
        "seed": s.get("seed"),
        "white_level": sess.white_level,
        "rig": rig,
        "phases": out_phases,
        "images": sum(p["images"] for p in out_phases.values()),
        "bytes": sum(p["bytes"] for p in out_phases.values()),
        "views": len(sess.views()),
        "planned_per_phase": planned_counts(sess),
        "simulated": sess.is_simulated,
        "manifest_lines": sum(1 for _ in read_manifest(root / "manifest.jsonl")),
    }
