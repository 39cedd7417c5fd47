"""Capture plans: what to photograph, in which order, with which exposures.

A plan is a TOML file (or a built-in, ``builtin:tiny`` / ``builtin:demo`` /
``builtin:paper``) parsed into frozen dataclasses. Every error names the key::

    [plan]
    name = "tiny"
    seed = 7                      # master seed; patterns derive theirs from it
    cameras = [0, 2, 4]           # camera indices (rig geometry order); default all
    half_float = false            # store EXR as 16-bit floats (clamped, warned)
    exr_compression = "rle"       # none | rle | zip | zips | piz | zstd (see acquire/exr.py)

    [table]
    steps = 4                     # or step_deg = 90.0
    start_deg = 0.0

    [exposures]
    default_s = [0.02]            # bracket used by phases that give none

    [timing]                      # only for estimates (dry run)
    per_image_s = 0.05            # readout + transfer + write per image
    settle_s = 0.1                # per state change (displays, lights)
    operator_s = 30.0             # per manual step

    [phases.calibration]          # ChArUco board on the table
    table_deg = [0, 90, 180, 270] # or count = 4
    charuco = { squares_x = 7, squares_y = 5, square_m = 0.04, marker_m = 0.03 }
    level = 255                   # all lights at this DMX level
    lights_deg = 0.0              # light-array angle
    exposures_s = [0.02]          # optional per-phase bracket

    [phases.matting]              # K random patterns + complements + backdrops off
    patterns = 2
    object_absent = true          # the same patterns with the object removed
    cell_px = 4                   # pattern cells, in display pattern pixels
    seed = 11                     # default: derived from [plan].seed
    level = 255                   # lights during matting (0 = off)
    lights_deg = "table"          # or a fixed angle

    [phases.lightfield]           # fixed lighting that rotates with the object
    level = 255
    lights_deg = "table"

    [phases.reflectance]          # one light at a time, each light at each array angle
    array_steps = 4               # or array_deg = [0, 90, ...]
    lights = [0, 1, 2, 3]         # default: every light of the rig
    level = 255
    lamp_radius_m = 0.2           # optional: the lamps' emitting radius the plan needs (diffusers)

    [phases.natural]              # natural images, one display at a time (alias: envmatte)
    images = 200                  # N per display domain (a count), or a list of image paths
    sources = ["probes", "noise"] # HDR probe crops/rotations, 1/f noise, "user" (user_images)
    user_images = ["a.png"]       # with "user": shown first, the rest of N from the others
    displays = ["back", "bottom"] # illumination domains (default: every display of the rig)
    kernels = 25                  # K of the estimate; N >= K is required
    level = 0
    seed = 13

Table angles are given once (``[table]``) and shared by every object phase; the
calibration phase has its own list.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast
from collections.abc import Mapping

from ..charuco import CharucoSpec
from ..errors import ConfigError
from ..tomlio import read_toml

if TYPE_CHECKING:
    from .exr import ExrCompression

__all__ = [
    "BUILTIN_PLANS",
    "CapturePlan",
    "CalibrationPhase",
    "MattingPhase",
    "LightfieldPhase",
    "ReflectancePhase",
    "EnvmattePhase",
    "NaturalPhase",
    "NATURAL_SOURCES",
    "Timing",
    "load_plan",
    "parse_plan",
]

PLAN_PHASES = ("calibration", "matting", "lightfield", "reflectance", "envmatte")
BUILTIN_PLANS = ("tiny", "demo", "paper", "natural")
#: where the natural phase's images come from (see :func:`~opacityhull.acquire.patterns.plan_patterns`)
NATURAL_SOURCES = ("probes", "noise", "user")
#: ``[phases.natural]`` and its older name ``[phases.envmatte]`` are one phase
PHASE_ALIASES = {"natural": "envmatte"}
_BUILTIN_DIR = Path(__file__).with_name("plans")


# --------------------------------------------------------------------------- helpers


def _check_keys(where: str, d: Mapping, allowed: set[str]) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _table(where: str, d: Mapping, key: str) -> dict:
    v = d.get(key, {})
    if not isinstance(v, Mapping):
        raise ConfigError(f"{where}.{key}: expected a table, got {v!r}")
    return dict(v)


def _number(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _all_count_or_ids(at: str, v, item: str, expected: str, *, min_id: int | None = None):
    """A selection of cameras or lights: ``"all"`` or absent (None), a count > 0 (int)
    or a list of distinct ids (tuple); ``item`` is ``"camera index"``, ``"light id"``."""
    if v is None or v == "all":
        return None
    if isinstance(v, int) and not isinstance(v, bool):
        if v <= 0:
            raise ConfigError(f"{at}: a {item.split()[0]} count must be > 0, got {v}")
        return v
    if (
        not isinstance(v, list)
        or not v
        or not all(isinstance(x, int) and not isinstance(x, bool) and (min_id is None or x >= min_id) for x in v)
    ):
        raise ConfigError(f'{at}: expected "all" or {expected}, got {v!r}')
    if len(set(v)) != len(v):
        raise ConfigError(f"{at}: duplicate {item} in {v}")
    return tuple(v)


def _int(where: str, d: Mapping, key: str, default: int, *, lo: int | None = None, hi: int | None = None) -> int:
    v = d.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ConfigError(f"{where}.{key}: expected an integer, got {v!r}")
    if lo is not None and v < lo:
        raise ConfigError(f"{where}.{key}: must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        raise ConfigError(f"{where}.{key}: must be <= {hi}, got {v}")
    return int(v)


def _bool(where: str, d: Mapping, key: str, default: bool) -> bool:
    v = d.get(key, default)
    if not isinstance(v, bool):
        raise ConfigError(f"{where}.{key}: expected true or false, got {v!r}")
    return v


def _exposures(where: str, v: Any) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)):
        raise ConfigError(f"{where}: expected a list of exposure times in seconds, got {v!r}")
    if len(v) == 0:
        raise ConfigError(f"{where}: the exposure list is empty; give at least one exposure time in seconds")
    out = []
    for i, x in enumerate(v):
        t = _number(f"{where}[{i}]", x)
        if t <= 0:
            raise ConfigError(f"{where}[{i}]: exposure must be > 0 s, got {t}")
        out.append(t)
    if len(set(out)) != len(out):
        raise ConfigError(f"{where}: duplicate exposure times in {out}")
    return tuple(sorted(out))


def _angle_list(where: str, v: Any) -> tuple[float, ...]:
    if not isinstance(v, (list, tuple)) or len(v) == 0:
        raise ConfigError(f"{where}: expected a non-empty list of angles in degrees, got {v!r}")
    out = [round(_number(f"{where}[{i}]", x) % 360.0, 6) for i, x in enumerate(v)]
    if len(set(out)) != len(out):
        raise ConfigError(f"{where}: duplicate angles (modulo 360) in {list(v)}")
    return tuple(out)


#: Most positions of a sweep (0.01° apart): more is a typo, and would be built in memory.
MAX_SWEEP_STEPS = 36000


def _sweep(
    where: str, d: Mapping, *, steps_key: str, step_key: str, list_key: str | None, default_steps: int
) -> tuple[float, ...]:
    """Angles from ``steps`` (evenly over 360), ``step_deg`` or an explicit list."""
    given = [k for k in (steps_key, step_key, list_key) if k and k in d]
    if len(given) > 1:
        raise ConfigError(f"{where}: give only one of {given}")
    start = _number(f"{where}.start_deg", d.get("start_deg", 0.0))
    if list_key and list_key in d:
        return _angle_list(f"{where}.{list_key}", d[list_key])
    if step_key in d:
        step = _number(f"{where}.{step_key}", d[step_key])
        if not step >= 360.0 / MAX_SWEEP_STEPS or step > 360:
            raise ConfigError(
                f"{where}.{step_key}: must be in [{360.0 / MAX_SWEEP_STEPS:g}, 360] degrees "
                f"(at most {MAX_SWEEP_STEPS} steps), got {step}"
            )
        # whole sweep without repeating 0 = 360: 360/step angles when it divides, else ceil
        n = (
            int(round(360.0 / step))
            if abs(360.0 / step - round(360.0 / step)) < 1e-9
            else int(math.floor(360.0 / step)) + 1
        )
        angles = [start + i * step for i in range(n)]
    else:
        v = d.get(steps_key, default_steps)
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"{where}.{steps_key}: expected an integer, got {v!r}")
        if not 0 < v <= MAX_SWEEP_STEPS:
            # a mistyped count (1e11) built the angle list until memory ran out
            raise ConfigError(f"{where}.{steps_key}: must be > 0 and at most {MAX_SWEEP_STEPS}, got {v}")
        angles = [start + i * 360.0 / v for i in range(v)]
    out = tuple(round(a % 360.0, 6) for a in angles)
    if len(set(out)) != len(out):
        raise ConfigError(f"{where}: angles repeat modulo 360 ({out})")
    return out


def _level(where: str, d: Mapping, default: int) -> int:
    return _int(where, d, "level", default, lo=0, hi=255)


def _lights_deg(where: str, d: Mapping, default) -> float | str:
    v = d.get("lights_deg", default)
    if v == "table":
        return "table"
    if isinstance(v, str):
        raise ConfigError(f'{where}.lights_deg: expected a number of degrees or "table", got {v!r}')
    return round(_number(f"{where}.lights_deg", v) % 360.0, 6)


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True, kw_only=True)
class Timing:
    """Declared per-image and per-step costs used by estimates (seconds)."""

    per_image_s: float = 0.05
    settle_s: float = 0.1
    operator_s: float = 30.0


@dataclass(frozen=True, kw_only=True)
class CalibrationPhase:
    table_deg: tuple[float, ...]
    charuco: CharucoSpec
    level: int = 255
    lights_deg: float = 0.0
    exposures_s: tuple[float, ...] | None = None


@dataclass(frozen=True, kw_only=True)
class MattingPhase:
    patterns: int
    object_absent: bool = True
    cell_px: int = 4
    seed: int = 0
    level: int = 255
    lights_deg: float | str = "table"
    exposures_s: tuple[float, ...] | None = None

    @property
    def pattern_ids(self) -> tuple[int, ...]:
        """Random pattern j (1-based) has id 2j-1, its complement id 2j."""
        return tuple(range(1, 2 * self.patterns + 1))


@dataclass(frozen=True, kw_only=True)
class LightfieldPhase:
    level: int = 255
    lights_deg: float | str = "table"
    exposures_s: tuple[float, ...] | None = None


@dataclass(frozen=True, kw_only=True)
class ReflectancePhase:
    array_deg: tuple[float, ...]
    lights: tuple[int, ...] | int | None = None  # ids, a count (evenly spread), None = every light
    level: int = 255
    exposures_s: tuple[float, ...] | None = None
    #: the lamps' emitting radius this plan needs, metres (diffusers fitted for it); None =
    #: the rig's lamps as they are. See :func:`~opacityhull.acquire.schedule.lamps_for_plan`.
    lamp_radius_m: float | None = None


@dataclass(frozen=True, kw_only=True)
class NaturalPhase:
    """Natural images on the displays (Matusik, Loper & Pfister 2004), one display at a
    time: each display in ``displays`` is its own illumination domain, shown N images
    while every other display is black.

    ``images`` is N (a count) or, for the older ``[phases.envmatte]`` form, a list of
    image paths (then ``sources == ("user",)`` and N = their number). With a count, the
    user images (if ``"user"`` is a source) come first and the rest alternate between
    the other sources. ``displays`` None = every display of the rig, in rig order."""

    images: int | tuple[str, ...]
    level: int = 0
    seed: int = 0
    lights_deg: float | str = "table"
    exposures_s: tuple[float, ...] | None = None
    sources: tuple[str, ...] = ("probes", "noise")
    user_images: tuple[str, ...] = ()
    displays: tuple[str, ...] | None = None
    kernels: int = 25

    @property
    def count(self) -> int:
        """N, images per display domain."""
        return self.images if isinstance(self.images, int) else len(self.images)

    def image_sources(self) -> list[str]:
        """Per image k < N: ``"user:<path>"``, ``"probes"`` or ``"noise"``."""
        if not isinstance(self.images, int):
            return [f"user:{p}" for p in self.images]
        out = [f"user:{p}" for p in self.user_images] if "user" in self.sources else []
        gen = [s for s in self.sources if s != "user"]
        k = 0
        while len(out) < self.images:
            out.append(gen[k % len(gen)])
            k += 1
        return out


#: the older name of the phase (same schedule, same session phase ``envmatte``)
EnvmattePhase = NaturalPhase


@dataclass(frozen=True, kw_only=True)
class CapturePlan:
    """A parsed capture plan. ``raw`` is the TOML table it came from (recorded in the
    session as ``[plan]``); ``source`` says where it was read from."""

    name: str
    seed: int
    table_deg: tuple[float, ...]
    default_exposures_s: tuple[float, ...]
    cameras: tuple[int, ...] | int | None = None  # indices, a count (evenly spread), None = all
    half_float: bool = False
    exr_compression: ExrCompression = "rle"
    timing: Timing = Timing()
    calibration: CalibrationPhase | None = None
    matting: MattingPhase | None = None
    lightfield: LightfieldPhase | None = None
    reflectance: ReflectancePhase | None = None
    envmatte: NaturalPhase | None = None
    source: str = ""
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def phases(self) -> tuple[str, ...]:
        return tuple(p for p in PLAN_PHASES if getattr(self, p) is not None)

    @property
    def natural(self) -> NaturalPhase | None:
        """The natural-illumination phase (stored as ``envmatte``, its session phase name)."""
        return self.envmatte

    def exposures(self, phase: str) -> tuple[float, ...]:
        ph = getattr(self, phase)
        return ph.exposures_s if ph is not None and ph.exposures_s else self.default_exposures_s

    def to_dict(self) -> dict:
        """The plan as a TOML-ready table (what ``session.toml [plan]`` stores)."""
        return dict(self.raw)


# --------------------------------------------------------------------------- parsing


def parse_plan(
    d: Mapping[str, Any], *, where: str = "plan", source: str = "", base_dir: Path | None = None
) -> CapturePlan:
    """Parse a plan table (the whole TOML document) into a :class:`CapturePlan`.

    Raises :class:`~opacityhull.errors.ConfigError` naming ``where`` and the key.
    """
    if not isinstance(d, Mapping):
        raise ConfigError(f"{where}: expected a table")
    _check_keys(where, d, {"plan", "table", "exposures", "timing", "phases"})
    p = _table(where, d, "plan")
    _check_keys(f"{where}: [plan]", p, {"name", "seed", "cameras", "half_float", "exr_compression", "description"})
    from .exr import COMPRESSIONS

    compression = p.get("exr_compression", "rle")
    if compression not in COMPRESSIONS:
        raise ConfigError(f"{where}: [plan].exr_compression: expected one of {list(COMPRESSIONS)}, got {compression!r}")
    name = p.get("name", "unnamed")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}: [plan].name: expected a non-empty string, got {name!r}")
    seed = _int(f"{where}: [plan]", p, "seed", 0, lo=0)
    cams = _all_count_or_ids(
        f"{where}: [plan].cameras", p.get("cameras"), "camera index", "a list of camera indices", min_id=0
    )

    t = _table(where, d, "table")
    _check_keys(f"{where}: [table]", t, {"steps", "step_deg", "start_deg", "angles_deg"})
    table_deg = _sweep(
        f"{where}: [table]", t, steps_key="steps", step_key="step_deg", list_key="angles_deg", default_steps=1
    )

    e = _table(where, d, "exposures")
    _check_keys(f"{where}: [exposures]", e, {"default_s"})
    default_exp = _exposures(f"{where}: [exposures].default_s", e.get("default_s", [0.02]))

    tm = _table(where, d, "timing")
    _check_keys(f"{where}: [timing]", tm, {"per_image_s", "settle_s", "operator_s"})
    timing_kw = {}
    for k in ("per_image_s", "settle_s", "operator_s"):
        if k in tm:
            v = _number(f"{where}: [timing].{k}", tm[k])
            if v < 0:
                raise ConfigError(f"{where}: [timing].{k}: must be >= 0, got {v}")
            timing_kw[k] = v
    timing = Timing(**timing_kw)

    phases = _table(where, d, "phases")
    for alias, canon in PHASE_ALIASES.items():
        if alias in phases:
            if canon in phases:
                raise ConfigError(f"{where}: [phases.{alias}] and [phases.{canon}] are the same phase; give one")
            phases = {(canon if k == alias else k): v for k, v in phases.items()}
            phase_name = {canon: alias}
            break
    else:
        phase_name = {}
    unknown = sorted(set(phases) - set(PLAN_PHASES))
    if unknown:
        raise ConfigError(
            f"{where}: unknown phase(s) {['phases.' + u for u in unknown]}; "
            f"known phases: {list(PLAN_PHASES) + list(PHASE_ALIASES)}"
        )
    if not phases:
        raise ConfigError(f"{where}: no [phases.*] table; give at least one of {list(PLAN_PHASES)}")
    kw: dict[str, Any] = {}

    def ph_table(name):
        return _table(f"{where}: [phases]", phases, name)

    def ph_exp(w, ph):
        return _exposures(f"{w}.exposures_s", ph["exposures_s"]) if "exposures_s" in ph else None

    if "calibration" in phases:
        ph = ph_table("calibration")
        w = f"{where}: [phases.calibration]"
        _check_keys(w, ph, {"table_deg", "count", "start_deg", "charuco", "level", "lights_deg", "exposures_s"})
        angles = _sweep(w, ph, steps_key="count", step_key="step_deg", list_key="table_deg", default_steps=4)
        ch = ph.get("charuco", {})
        if not isinstance(ch, Mapping):
            raise ConfigError(f"{w}.charuco: expected a table, got {ch!r}")
        try:
            spec = CharucoSpec.from_dict(dict(ch), where=f"{w}.charuco")
        except TypeError as err:
            raise ConfigError(f"{w}.charuco: {err}") from None
        ld = _lights_deg(w, ph, 0.0)
        if isinstance(ld, str):  # "table": the array follows the table, meaningless for calibration
            raise ConfigError(f"{w}.lights_deg: must be a number for calibration")
        kw["calibration"] = CalibrationPhase(
            table_deg=angles, charuco=spec, level=_level(w, ph, 255), lights_deg=ld, exposures_s=ph_exp(w, ph)
        )
    if "matting" in phases:
        ph = ph_table("matting")
        w = f"{where}: [phases.matting]"
        _check_keys(w, ph, {"patterns", "object_absent", "cell_px", "seed", "level", "lights_deg", "exposures_s"})
        kw["matting"] = MattingPhase(
            patterns=_int(w, ph, "patterns", 2, lo=1, hi=100),
            object_absent=_bool(w, ph, "object_absent", True),
            cell_px=_int(w, ph, "cell_px", 4, lo=1),
            seed=_int(w, ph, "seed", seed * 1000 + 1, lo=0),
            level=_level(w, ph, 255),
            lights_deg=_lights_deg(w, ph, "table"),
            exposures_s=ph_exp(w, ph),
        )
    if "lightfield" in phases:
        ph = ph_table("lightfield")
        w = f"{where}: [phases.lightfield]"
        _check_keys(w, ph, {"level", "lights_deg", "exposures_s"})
        kw["lightfield"] = LightfieldPhase(
            level=_level(w, ph, 255), lights_deg=_lights_deg(w, ph, "table"), exposures_s=ph_exp(w, ph)
        )
    if "reflectance" in phases:
        ph = ph_table("reflectance")
        w = f"{where}: [phases.reflectance]"
        _check_keys(
            w,
            ph,
            {
                "array_steps",
                "array_step_deg",
                "array_deg",
                "start_deg",
                "lights",
                "level",
                "exposures_s",
                "lamp_radius_m",
            },
        )
        arr = _sweep(w, ph, steps_key="array_steps", step_key="array_step_deg", list_key="array_deg", default_steps=1)
        lights = _all_count_or_ids(f"{w}.lights", ph.get("lights"), "light id", "a non-empty list of light ids")
        level = _level(w, ph, 255)
        if level == 0:
            raise ConfigError(f"{w}.level: must be > 0 (one light at a time needs the light on)")
        radius = None
        if "lamp_radius_m" in ph:
            radius = _number(f"{w}.lamp_radius_m", ph["lamp_radius_m"])
            if not (math.isfinite(radius) and radius > 0):
                raise ConfigError(
                    f"{w}.lamp_radius_m: expected a lamp radius > 0 in metres, got {ph['lamp_radius_m']!r}"
                )
        kw["reflectance"] = ReflectancePhase(
            array_deg=arr, lights=lights, level=level, exposures_s=ph_exp(w, ph), lamp_radius_m=radius
        )
    if "envmatte" in phases:
        kw["envmatte"] = _parse_natural(
            f"{where}: [phases.{phase_name.get('envmatte', 'envmatte')}]",
            ph_table("envmatte"),
            seed=seed,
            base_dir=base_dir,
            exposures=ph_exp,
            strict=phase_name.get("envmatte") == "natural",
        )

    return CapturePlan(
        name=name,
        seed=seed,
        table_deg=table_deg,
        default_exposures_s=default_exp,
        cameras=cams,
        half_float=_bool(f"{where}: [plan]", p, "half_float", False),
        exr_compression=cast("ExrCompression", compression),  # checked against COMPRESSIONS above
        timing=timing,
        source=source,
        raw=_plain(d),
        **kw,
    )


def _user_image(w: str, s: Any, base_dir: Path | None) -> str:
    """A user image path, resolved against the plan's folder, that exists and is an
    image OpenCV can decode (checked by its signature here, fully when shown)."""
    import cv2

    if not isinstance(s, str) or not s:
        raise ConfigError(f"{w}: expected an image path, got {s!r}")
    pth = Path(s)
    if not pth.is_absolute() and base_dir is not None:
        pth = base_dir / pth
    if not pth.is_file():
        raise ConfigError(f"{w}: image {pth} not found")
    try:
        ok = cv2.haveImageReader(str(pth))
    except cv2.error:  # pragma: no cover - OpenCV refuses odd names
        ok = False
    if not ok:
        raise ConfigError(f"{w}: {pth} is not an image OpenCV can read (expected PNG, JPEG, TIFF, EXR, HDR, ...)")
    return str(pth)


def _parse_natural(
    w: str, ph: Mapping, *, seed: int, base_dir: Path | None, exposures, strict: bool = True
) -> NaturalPhase:
    """``strict`` (``[phases.natural]``): N >= K always; the older ``[phases.envmatte]``
    name only checks it when ``kernels`` is given (it was not made for estimation)."""
    _check_keys(
        w, ph, {"images", "level", "seed", "lights_deg", "exposures_s", "sources", "user_images", "displays", "kernels"}
    )
    kernels = _int(w, ph, "kernels", 25, lo=1, hi=255)
    imgs = ph.get("images", kernels if strict or "kernels" in ph else 2)
    user: tuple[str, ...] = ()
    if isinstance(imgs, list):
        if not imgs:
            raise ConfigError(f"{w}.images: expected a count or a non-empty list of image paths, got {imgs!r}")
        if "sources" in ph or "user_images" in ph:
            raise ConfigError(f"{w}: images is a list of paths; give a count with sources/user_images instead")
        imgs = tuple(_user_image(f"{w}.images[{i}]", s, base_dir) for i, s in enumerate(imgs))
        sources: tuple[str, ...] = ("user",)
    else:
        imgs = _int(w, ph, "images", 2, lo=1, hi=4000)
        src = ph.get("sources", ["probes", "noise"])
        if (
            not isinstance(src, list)
            or not src
            or not all(isinstance(x, str) for x in src)
            or len(set(src)) != len(src)
        ):
            raise ConfigError(
                f"{w}.sources: expected a non-empty list of distinct names from {list(NATURAL_SOURCES)}, got {src!r}"
            )
        bad = [x for x in src if x not in NATURAL_SOURCES]
        if bad:
            raise ConfigError(f"{w}.sources: unknown source(s) {bad}; expected names from {list(NATURAL_SOURCES)}")
        sources = tuple(src)
        ui = ph.get("user_images", [])
        if not isinstance(ui, list):
            raise ConfigError(f"{w}.user_images: expected a list of image paths, got {ui!r}")
        if ui and "user" not in sources:
            raise ConfigError(f'{w}.user_images: given but "user" is not in sources {list(sources)}')
        if "user" in sources and not ui:
            raise ConfigError(f'{w}.sources: "user" needs user_images = [paths]')
        user = tuple(_user_image(f"{w}.user_images[{i}]", s, base_dir) for i, s in enumerate(ui))
        if len(user) > imgs:
            raise ConfigError(f"{w}: {len(user)} user_images but images = {imgs}; N must be >= the user images")
        if len(user) < imgs and sources == ("user",):
            raise ConfigError(
                f"{w}: images = {imgs} but only {len(user)} user_images and no other source; "
                f'add "probes" or "noise" to sources or lower images'
            )
    n = imgs if isinstance(imgs, int) else len(imgs)
    if (strict or "kernels" in ph) and n < kernels:
        raise ConfigError(
            f"{w}: images = {n} per display but kernels = {kernels}: the estimate needs N >= K "
            f"(the paper uses N = 200, K = 25); raise images or lower kernels"
        )
    disp = ph.get("displays")
    if disp is not None:
        if disp != "all" and (
            not isinstance(disp, list)
            or not disp
            or not all(isinstance(x, str) and x for x in disp)
            or len(set(disp)) != len(disp)
        ):
            raise ConfigError(
                f'{w}.displays: expected "all" or a non-empty list of distinct display names, got {disp!r}'
            )
        disp = None if disp == "all" else tuple(disp)
    return NaturalPhase(
        images=imgs,
        level=_level(w, ph, 0),
        seed=_int(w, ph, "seed", seed * 1000 + 2, lo=0),
        lights_deg=_lights_deg(w, ph, "table"),
        exposures_s=exposures(w, ph),
        sources=sources,
        user_images=user,
        displays=disp,
        kernels=kernels,
    )


def _plain(d):
    if isinstance(d, Mapping):
        return {str(k): _plain(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_plain(v) for v in d]
    return d


def load_plan(spec: str | Path) -> CapturePlan:
    """A plan from ``builtin:NAME`` or a TOML path."""
    s = str(spec)
    if s.startswith("builtin:"):
        name = s.split(":", 1)[1]
        if name not in BUILTIN_PLANS:
            raise ConfigError(
                f"--plan {s}: no built-in plan {name!r}; built-ins: " + ", ".join(f"builtin:{n}" for n in BUILTIN_PLANS)
            )
        path = _BUILTIN_DIR / f"{name}.toml"
        return parse_plan(read_toml(path, error=ConfigError, what="built-in plan"), where=s, source=s)
    path = Path(s)
    if not path.is_file():
        raise ConfigError(f"--plan {s}: file not found (give a plan TOML or builtin:" + "|".join(BUILTIN_PLANS) + ")")
    d = read_toml(path, error=ConfigError, what="plan TOML")
    return parse_plan(d, where=str(path), source=str(path.resolve()), base_dir=path.parent)
