"""The capture session on disk: written by ``acquire``, read by ``reconstruct``.

Neither stage imports the other; this module is the contract between them.

Layout of a session folder::

    session.toml        [session] format, software version, created, rig/plan source,
                        seed; [rig] the rig geometry table (riggeometry schema);
                        [plan] the plan as run; [patterns] what each pattern id is
    manifest.jsonl      one JSON record per image, appended only after the image file
                        was atomically renamed into place, then flushed and fsynced
    images/<phase>/<camera>/<file>.exr    linear float images (EXR)
    patterns/<display>/p<id>.png          backdrop patterns exactly as uploaded (8-bit)
    calibration/<camera>.yaml             optional: known intrinsics + rig_from_cam
    cameras/                              optional: COLMAP text model giving each view's
                                          camera directly (imported image sets)
    groundtruth/                          simulated sessions only: true cameras,
                                          coverage alpha per view, object mesh, lights

A manifest record (see :class:`ShotRecord`) says which phase, camera, table angle,
light-array angle, light or pattern and exposure produced the image, its path relative
to the session, its sha256 and size. ``shot`` identifies the shot independently of
the exposure bracket; ``id`` is unique per image. HDR merges (a separate step) append
records with ``kind = "hdr"`` that list their ``sources``.

Image values are linear sensor values; ``value = gain * exposure_s * radiance`` with
the camera's ``gain`` from the rig geometry, so :meth:`Session.load_radiance` returns
radiance in the scene's units regardless of exposure.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from collections.abc import Iterator

import numpy as np

if TYPE_CHECKING:
    from .camera import Camera

from . import __version__
from .errors import FormatError, InputError
from .riggeometry import RigGeometry, view_id
from .tomlio import read_toml, toml_dumps  # toml_dumps: also still importable from here

log = logging.getLogger(__name__)

__all__ = [
    "SESSION_FORMAT",
    "PHASES",
    "PHASE_ALIASES",
    "phase_names",
    "ShotRecord",
    "Session",
    "SessionWriter",
    "sha256_file",
    "shot_key",
    "check_manifest",
    "require_manifest_ok",
    "check_finite",
    "read_manifest",
    "toml_dumps",
]

SESSION_FORMAT = "opacityhull-session/1"
#: "natural" and "envmatte" both hold natural-illumination images (the runner records the
#: plan's [phases.natural] as "envmatte"; readers accept either)
PHASES = ("calibration", "matting", "lightfield", "reflectance", "envmatte", "natural", "mask")
#: phase names that hold the same images (a selection by one name matches the other)
PHASE_ALIASES = {"natural": ("natural", "envmatte"), "envmatte": ("envmatte", "natural")}


def phase_names(phases) -> set[str]:
    """The recorded phase names a user's phase selection matches.

    ``natural`` and ``envmatte`` select each other (:data:`PHASE_ALIASES`): a plan's
    ``[phases.natural]`` is recorded as ``envmatte`` by the runner, so ``--phase natural``
    must find those images. Unknown names pass through unchanged (callers validate them
    against :data:`PHASES`).
    """
    return {q for p in phases for q in PHASE_ALIASES.get(p, (p,))}


def sha256_file(path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def shot_key(
    phase: str,
    camera: int,
    table_deg: float,
    *,
    lights_deg: float | None = None,
    light: int | None = None,
    pattern: int | None = None,
    object_present: bool = True,
) -> str:
    """Bracket-independent shot identifier, also the stem of its image files.

    e.g. ``matting/c0_t030.000/p003`` (``p003_bg`` with the object removed, ``off`` with
    the backdrops blank), ``lightfield/c0_t030.000/img`` or
    ``reflectance/c1_t000.000/a045.000_l2``.
    """
    parts = [phase, view_id(camera, table_deg)]
    leaf = []
    if lights_deg is not None:
        leaf.append(f"a{float(lights_deg) % 360.0:07.3f}")
    if light is not None:
        leaf.append(f"l{int(light)}")
    if pattern is not None:
        leaf.append(f"p{int(pattern):03d}")
    elif phase in ("matting", "envmatte", "natural"):
        leaf.append("off")
    if not object_present:
        leaf.append("bg")
    return "/".join(parts + ["_".join(leaf) if leaf else "img"])


@dataclass(frozen=True)
class ShotRecord:
    """One image of a session (one line of ``manifest.jsonl``).

    Attributes
    ----------
    id : unique image id (``shot`` + ``/e<bracket index>``, or ``/hdr``).
    shot : bracket-independent shot key (:func:`shot_key`).
    phase : one of :data:`PHASES`.
    camera : index of the physical camera (rig geometry order).
    table_deg : turntable angle in degrees.
    lights_deg : light-array angle in degrees, or None when irrelevant.
    light : light id lit alone (reflectance phase), or None.
    pattern : backdrop pattern id shown on every display, None = displays blank.
    object_present : False for the object-absent backdrop captures.
    exposure_s : exposure time in seconds (None for an HDR merge).
    path : image path relative to the session folder (POSIX separators).
    sha256, bytes : of the file as written.
    kind : "raw" (a capture) or "hdr" (a merge of ``sources``).
    extra : free-form details (lights on in the lightfield phase, seed, ...).
    """

    id: str
    shot: str
    phase: str
    camera: int
    table_deg: float
    path: str
    sha256: str
    bytes: int
    exposure_s: float | None = None
    lights_deg: float | None = None
    light: int | None = None
    pattern: int | None = None
    object_present: bool = True
    kind: str = "raw"
    sources: tuple[str, ...] = ()
    extra: dict = field(default_factory=dict)

    @property
    def view(self) -> str:
        return view_id(self.camera, self.table_deg)

    def to_json(self) -> str:
        d = asdict(self)
        d["sources"] = list(self.sources)
        return json.dumps(d, sort_keys=True, separators=(",", ":"))

    @classmethod
    def from_dict(cls, d: dict, where: str = "manifest") -> ShotRecord:
        if not isinstance(d, dict):
            raise FormatError(f"{where}: record is a JSON {type(d).__name__}, expected an object")
        try:
            d = dict(d)
            d["sources"] = tuple(d.get("sources", ()))
            rec = cls(**d)
        except TypeError as e:
            raise FormatError(f"{where}: record does not match the session format ({e})") from None
        _check_record_types(rec, d.get("id"), where)
        return rec


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: Field → (accepts, what is expected), checked on every record read.
_RECORD_TYPES = {
    "id": (lambda v: isinstance(v, str) and bool(v), "a non-empty string"),
    "shot": (lambda v: isinstance(v, str) and bool(v), "a non-empty string"),
    "phase": (lambda v: v in PHASES, f"one of {', '.join(PHASES)}"),
    "camera": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0"),
    "table_deg": (lambda v: _is_num(v) and np.isfinite(v), "a finite number (degrees)"),
    "path": (
        lambda v: isinstance(v, str) and bool(v) and not v.startswith("/") and ".." not in v.split("/"),
        "a relative path inside the session",
    ),
    "sha256": (
        lambda v: isinstance(v, str) and len(v) == 64 and all(c in "0123456789abcdef" for c in v),
        "64 lowercase hex digits",
    ),
    "bytes": (lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0"),
    "exposure_s": (lambda v: v is None or (_is_num(v) and np.isfinite(v) and v > 0), "null or a number > 0 (seconds)"),
    "lights_deg": (lambda v: v is None or (_is_num(v) and np.isfinite(v)), "null or a finite number (degrees)"),
    "light": (lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool)), "null or an integer"),
    "pattern": (lambda v: v is None or (isinstance(v, int) and not isinstance(v, bool)), "null or an integer"),
    "object_present": (lambda v: isinstance(v, bool), "true or false"),
    "kind": (lambda v: v in ("raw", "hdr"), '"raw" or "hdr"'),
    "sources": (lambda v: all(isinstance(x, str) for x in v), "a list of image ids"),
    "extra": (lambda v: isinstance(v, dict), "an object"),
}


def _check_record_types(rec: ShotRecord, rid, where: str) -> None:
    for name, (ok, want) in _RECORD_TYPES.items():
        v = getattr(rec, name)
        if not ok(v):
            who = f" {rid!r}" if isinstance(rid, str) else ""
            raise FormatError(f"{where}: record{who}: {name} = {json.dumps(v, default=str)}, expected {want}")


# --------------------------------------------------------------------------- TOML


# --------------------------------------------------------------------------- reader


class Session:
    """A session folder opened for reading.

    Use :meth:`open`. Records whose ``kind`` is ``"hdr"`` supersede the raw brackets
    of the same shot in :meth:`load_radiance`.
    """

    def __init__(self, root: Path, meta: dict, records: list[ShotRecord]):
        self.root = root
        self.meta = meta
        # An image re-shot on resume (its file was corrupt) appends a second record
        # with the same id: the last record of an id wins.
        last: dict[str, int] = {}
        for i, r in enumerate(records):
            last[r.id] = i
        self.superseded = len(records) - len(last)
        self.records = [r for i, r in enumerate(records) if last[r.id] == i]
        self._by_shot: dict[str, list[ShotRecord]] = {}
        for r in self.records:
            self._by_shot.setdefault(r.shot, []).append(r)

    @classmethod
    def open_meta(cls, root) -> dict:
        """``session.toml`` of ``root``, checked (folder exists, valid TOML, format)."""
        root = Path(root)
        toml_path = root / "session.toml"
        if not root.exists():
            # a path that is not there is a typo (bad input, exit 2), not corrupt data
            raise InputError(f"{root}: no such session folder")
        if not root.is_dir():
            raise InputError(f"{root} is a file, expected a session folder")
        if not toml_path.is_file():
            raise FormatError(f"{root} is not a session: {toml_path} not found")
        meta = read_toml(toml_path, error=FormatError, what="session.toml")
        fmt = meta.get("session", {}).get("format")
        if fmt != SESSION_FORMAT:
            raise FormatError(f"{toml_path}: session format {fmt!r}, expected {SESSION_FORMAT!r}")
        return meta

    @classmethod
    def open(cls, root) -> Session:
        root = Path(root)
        meta = cls.open_meta(root)
        sess = cls(root, meta, list(read_manifest(root / "manifest.jsonl")))
        _ = sess.white_level  # checked now: a bad value must stop a build before its first step
        return sess

    # ---- metadata
    @property
    def geometry(self) -> RigGeometry:
        if "rig" not in self.meta:
            raise FormatError(f"{self.root / 'session.toml'}: no [rig] table")
        return RigGeometry.from_dict(self.meta["rig"], where=f"{self.root / 'session.toml'}:rig")

    @property
    def plan(self) -> dict:
        return self.meta.get("plan", {})

    @property
    def source(self) -> str:
        """``rig_source`` of the session: a rig TOML path or ``sim:<scene>``."""
        return self.meta.get("session", {}).get("rig_source", "")

    @property
    def white_level(self) -> float:
        """Sensor value at saturation (``[session] white_level``; 1.0 when not recorded).

        Raises :class:`FormatError` naming the file and key unless it is a finite number > 0."""
        v = self.meta.get("session", {}).get("white_level", 1.0)
        if not _is_num(v) or not np.isfinite(v) or v <= 0:
            raise FormatError(
                f"{self.root / 'session.toml'}: [session] white_level = {json.dumps(v, default=str)}, "
                "expected a finite number > 0 (the sensor value at saturation)"
            )
        return float(v)

    @property
    def charuco(self):
        """The calibration board (:class:`~opacityhull.charuco.CharucoSpec`) of the
        calibration phase (``[charuco]``), or None."""
        from .charuco import CharucoSpec

        d = self.meta.get("charuco")
        return None if not d else CharucoSpec.from_dict(d, where=f"{self.root / 'session.toml'}:charuco")

    @property
    def patterns(self) -> dict:
        """``[patterns]``: per pattern key (``p001``) its id, kind (random, complement,
        natural), phase, ``files`` per display, and for complements the id it inverts."""
        return dict(self.meta.get("patterns", {}))

    @property
    def camera_info(self) -> list[dict]:
        """``[[camera_info]]``: what each camera reported (name, size, white_level, linear)."""
        return list(self.meta.get("camera_info", []))

    @property
    def is_simulated(self) -> bool:
        return (self.root / "groundtruth").is_dir()

    # ---- records
    def select(self, *, phase=None, camera=None, table_deg=None, kind: str | None = "raw", **eq) -> list[ShotRecord]:
        """Records matching every given attribute (``kind=None`` for any kind)."""
        out = []
        for r in self.records:
            if phase is not None and r.phase != phase:
                continue
            if camera is not None and r.camera != camera:
                continue
            if table_deg is not None and abs(((r.table_deg - table_deg) + 180) % 360 - 180) > 1e-6:
                continue
            if kind is not None and r.kind != kind:
                continue
            if any(getattr(r, k) != v for k, v in eq.items()):
                continue
            out.append(r)
        return out

    def phases(self) -> set[str]:
        return {r.phase for r in self.records}

    def views(self, phase: str | None = None) -> list[tuple[int, float]]:
        """Sorted distinct (camera, table_deg) pairs with images (in ``phase`` if given)."""
        seen = {(r.camera, round(r.table_deg % 360.0, 6)) for r in self.records if phase is None or r.phase == phase}
        return sorted(seen)

    def shots(self, **kw) -> list[str]:
        return sorted({r.shot for r in self.select(kind=None, **kw)})

    def abspath(self, record: ShotRecord) -> Path:
        return self.root / record.path

    def load_image(self, record: ShotRecord) -> np.ndarray:
        from .imageio import read_image

        return read_image(self.abspath(record))

    def load_radiance(self, shot: str, *, saturation: float = 0.98) -> np.ndarray:
        """Radiance image (H, W, C) of a shot, float32.

        The HDR merge when there is one; otherwise the longest exposure in which no
        channel reaches ``saturation`` x white level in more than 0.1 % of pixels (or
        the shortest one), divided by ``gain * exposure_s``.
        """
        return self.load_radiance_clip(shot, saturation=saturation)[0]

    def load_radiance_clip(self, shot: str, *, saturation: float = 0.98) -> tuple[np.ndarray, float]:
        """:meth:`load_radiance` and the radiance at which that image's pixels clip:
        ``saturation * white_level / (gain * exposure_s)`` of the bracket chosen, inf for
        an HDR merge. One bracket choice for every reader, so a clip level always
        belongs to the image returned with it."""
        recs = self._by_shot.get(shot)
        if not recs:
            raise FormatError(f"{self.root}: no image for shot {shot!r} in the manifest")
        hdr = [r for r in recs if r.kind == "hdr"]
        if hdr:
            return self.load_image(hdr[-1]), float("inf")
        raws = sorted((r for r in recs if r.kind == "raw"), key=lambda r: r.exposure_s or 0.0)
        if not raws:
            raise FormatError(f"{self.root}: shot {shot!r} has no raw or HDR image")
        white = self.white_level
        cam_gain = self.gain(recs[0].camera)
        chosen, img = raws[0], None
        for r in reversed(raws):
            im = self.load_image(r)
            if np.mean(np.any(im[..., :3] >= saturation * white, axis=-1)) <= 1e-3 or r is raws[0]:
                chosen, img = r, im
                break
        if img is None:  # pragma: no cover - the loop always stops at raws[0]
            img = self.load_image(chosen)
        exp = chosen.exposure_s or 1.0
        return (img / np.float32(cam_gain * exp)).astype(np.float32), float(saturation * white / (cam_gain * exp))

    def gain(self, camera: int) -> float:
        """Camera ``camera``'s gain from the rig geometry (1.0 without a rig or camera),
        parsed once per session rather than once per image."""
        cache = self.__dict__.setdefault("_gains", {})
        if camera not in cache:
            cache[camera] = self._gain(camera)
        return cache[camera]

    def _gain(self, camera: int) -> float:
        if "rig" not in self.meta:  # an imported session: values are radiance already
            log.debug("%s: no [rig] table; camera %d gain 1.0", self.root / "session.toml", camera)
            return 1.0
        cams = self.geometry.cameras  # a corrupt [rig] table raises FormatError naming the key
        if not 0 <= int(camera) < len(cams):
            log.warning(
                "%s: camera %d is not among the rig's %d cameras; gain 1.0",
                self.root / "session.toml",
                camera,
                len(cams),
            )
            return 1.0
        return float(cams[int(camera)].gain)

    def pattern_image(self, display: str, pattern: int) -> np.ndarray:
        """The uploaded pattern (rows, cols, 3) as display drive values in [0, 1]."""
        from .imageio import read_png

        return read_png(self.root / "patterns" / display / f"p{int(pattern):03d}.png", linear=True)

    def calibration_cameras(self) -> dict[int, Camera] | None:
        """Known calibration (``calibration/<camera name>.yaml``) per camera index, or None."""
        from .camera import read_opencv_yaml

        d = self.root / "calibration"
        if not d.is_dir():
            return None
        out = {}
        for i, spec in enumerate(self.geometry.cameras):
            p = d / f"{spec.name}.yaml"
            if p.is_file():
                out[i] = read_opencv_yaml(p)
        return out or None

    def view_cameras(self) -> dict[str, Camera] | None:
        """Cameras given per view in ``cameras/`` (COLMAP text, names = view ids), or None."""
        from .camera import read_colmap_text

        d = self.root / "cameras"
        if not (d / "images.txt").is_file():
            return None
        return {name: cam.with_name(name) for name, cam in read_colmap_text(d)}

    @property
    def groundtruth_dir(self) -> Path | None:
        d = self.root / "groundtruth"
        return d if d.is_dir() else None


def read_manifest(path, *, problems: list[str] | None = None) -> Iterator[ShotRecord]:
    """Records of a ``manifest.jsonl``. A torn last line (crash mid-append) is skipped;
    a corrupt line elsewhere raises :class:`FormatError` naming the line — or, when a
    ``problems`` list is given, is skipped and its message appended there (``session
    verify`` reports every bad line instead of the first)."""
    path = Path(path)
    if not path.is_file():
        return iter(())
    lines = path.read_bytes().split(b"\n")
    out = []
    for i, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            try:
                d = json.loads(raw)
            except (json.JSONDecodeError, UnicodeDecodeError):
                if i >= len(lines) - 1:  # the last (unterminated) line: a torn append
                    continue
                raise FormatError(f"{path}:{i}: not valid JSON") from None
            out.append(ShotRecord.from_dict(d, where=f"{path}:{i}"))
        except FormatError as e:
            if problems is None:
                raise
            problems.append(str(e))
    return iter(out)


def check_manifest(session: Session, *, hash_files: bool = True, progress=None) -> list[str]:
    """Problems of a session's manifest against its files, as messages (empty = OK).

    Checks what ``build`` would otherwise trust: every listed image exists with the
    recorded size and sha256 (``hash_files=False`` checks sizes only), and an image id
    listed twice names the same file both times (a re-shoot on resume appends the same
    id and path; two different files under one id is a corrupt or hand-edited
    manifest). Messages name the manifest, the id and what differs.
    """
    manifest = session.root / "manifest.jsonl"
    problems: list[str] = []
    paths_by_id: dict[str, str] = {}
    for r in read_manifest(manifest):
        first = paths_by_id.setdefault(r.id, r.path)
        if first != r.path:
            problems.append(f"{manifest}: image id {r.id!r} is listed twice, for {first} and {r.path}")
    recs = session.records
    for k, r in enumerate(recs):
        p = session.root / r.path
        if not p.is_file():
            problems.append(f"{manifest}: {r.id!r}: {r.path} is missing")
        elif p.stat().st_size != r.bytes:
            problems.append(f"{manifest}: {r.id!r}: {r.path} has {p.stat().st_size} bytes, the manifest says {r.bytes}")
        elif hash_files and sha256_file(p) != r.sha256:
            problems.append(
                f"{manifest}: {r.id!r}: {r.path} has sha256 {sha256_file(p)[:12]}..., the manifest says "
                f"{r.sha256[:12]}..."
            )
        if progress is not None:
            progress(k + 1, len(recs))
    return problems


def require_manifest_ok(session: Session, *, hash_files: bool = True, progress=None) -> None:
    """Raise :class:`FormatError` listing :func:`check_manifest`'s problems (first five)."""
    problems = check_manifest(session, hash_files=hash_files, progress=progress)
    if problems:
        more = f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""
        raise FormatError(
            "; ".join(problems[:5]) + more + " — run `opacityhull session verify` and re-capture with --resume"
        )


def check_finite(image: np.ndarray, *, where: str) -> str | None:
    """A note when ``image`` holds NaN or Inf values, else None.

    ``where`` names the file or view. Use it where an image enters a computation that
    would silently turn NaN into black (matting) or Inf into 0 (reflectance)."""
    a = np.asarray(image)
    if a.dtype.kind != "f":
        return None
    bad = ~np.isfinite(a)
    if not bad.any():
        return None
    n_nan = int(np.isnan(a).sum())
    n_inf = int(bad.sum()) - n_nan
    px = int(bad.reshape(a.shape[0], a.shape[1], -1).any(axis=-1).sum()) if a.ndim >= 2 else int(bad.sum())
    return (
        f"{where}: {px} pixel(s) are not finite ({n_nan} NaN, {n_inf} Inf values) — a broken sensor read or "
        "a corrupt file"
    )


# --------------------------------------------------------------------------- writer


class SessionWriter:
    """Appends images to a session folder, never losing or duplicating one.

    Each image is written to a temporary file, fsynced and renamed into place; only
    then is its record appended to ``manifest.jsonl`` and the manifest fsynced. A crash
    at any point leaves at worst an image without a record (found by ``session
    verify`` as *unlisted*, and overwritten when the shot is re-taken on resume).
    """

    def __init__(self, root, *, fsync: bool = True):
        self.root = Path(root)
        self.fsync = fsync
        self._manifest = None
        self._ids: set[str] = set()

    # ---- lifecycle
    def create(self, meta: dict) -> SessionWriter:
        """Start a new session in an empty (or absent) folder; refuses a non-empty one."""
        from .imageio import atomic_path

        if self.root.exists() and any(self.root.iterdir()):
            raise InputError(f"{self.root} is not empty; use --resume to continue a session there")
        self.root.mkdir(parents=True, exist_ok=True)
        meta = dict(meta)
        s = dict(meta.get("session", {}))
        s.setdefault("format", SESSION_FORMAT)
        s.setdefault("software_version", __version__)
        s.setdefault("created_utc", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
        meta["session"] = s
        with atomic_path(self.root / "session.toml") as tmp:
            tmp.write_text(toml_dumps(meta))
        return self._open_manifest()

    def resume(self) -> SessionWriter:
        """Open an existing session for appending; returns self."""
        if not (self.root / "session.toml").is_file():
            raise InputError(f"{self.root} holds no session.toml; nothing to resume")
        return self._open_manifest()

    def _open_manifest(self) -> SessionWriter:
        path = self.root / "manifest.jsonl"
        # A torn last line (crash or full disk mid-append) is not a record: cut it off so
        # that it neither glues onto the next record nor sits corrupt mid-file.
        if path.is_file() and path.stat().st_size > 0:
            data = path.read_bytes()
            if not data.endswith(b"\n"):
                keep = data.rfind(b"\n") + 1
                with open(path, "r+b") as f:
                    f.truncate(keep)
                    f.flush()
                    os.fsync(f.fileno())
        self._ids = {r.id for r in read_manifest(path)}
        self._manifest = open(path, "ab", buffering=0)  # noqa: SIM115  open for the session, closed by close()
        return self

    def close(self) -> None:
        if self._manifest is not None:
            self._manifest.close()
            self._manifest = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    # ---- writing
    @property
    def ids(self) -> set[str]:
        return set(self._ids)

    def add_image(
        self,
        image: np.ndarray,
        *,
        id: str,
        shot: str,
        phase: str,
        camera: int,
        table_deg: float,
        rel_path: str,
        half: bool = False,
        **fields,
    ) -> ShotRecord:
        """Write ``image`` (EXR) at ``rel_path`` atomically and append its record."""
        from .imageio import write_exr

        if phase not in PHASES:
            raise InputError(f"unknown phase {phase!r}; expected one of {PHASES}")
        path = self.root / rel_path
        write_exr(path, image, half=half)
        return self.add_file(path, id=id, shot=shot, phase=phase, camera=camera, table_deg=table_deg, **fields)

    def add_file(
        self, path, *, id: str, shot: str, phase: str, camera: int, table_deg: float, replace: bool = False, **fields
    ) -> ShotRecord:
        """Append the record of a file already atomically in place inside the session.

        ``replace=True`` allows an id that is already listed (an image re-taken because
        its file was corrupt); readers take the last record of an id."""
        if self._manifest is None:
            raise InputError("session writer is not open (call create() or resume())")
        path = Path(path)
        rel = path.relative_to(self.root).as_posix()
        rec = ShotRecord(
            id=id,
            shot=shot,
            phase=phase,
            camera=int(camera),
            table_deg=float(table_deg),
            path=rel,
            sha256=sha256_file(path),
            bytes=path.stat().st_size,
            **fields,
        )
        if rec.id in self._ids and not replace:
            raise InputError(f"image id {rec.id!r} is already in {self.root / 'manifest.jsonl'}")
        line = (rec.to_json() + "\n").encode()
        start = self._manifest.tell()
        try:
            n = self._manifest.write(line)
            if n != len(line):
                raise OSError(28, f"short write to {self.root / 'manifest.jsonl'} ({n} of {len(line)} bytes)")
            if self.fsync:
                os.fsync(self._manifest.fileno())
        except OSError:
            # Never leave half a record behind (e.g. the disk filled up mid-line).
            try:
                self._manifest.truncate(start)
                self._manifest.seek(start)
            except OSError as e2:  # the write error is the one to report; verify notes the torn line
                log.warning("%s: could not cut the partial record (%s)", self.root / "manifest.jsonl", e2)
            raise
        self._ids.add(rec.id)
        return rec
