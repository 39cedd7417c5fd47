"""From a plan and a rig geometry to the ordered list of shots, and what they cost.

Pure functions, no devices: the runner executes the schedule, the dry run prices it.

Order (slow things outermost): the stages follow the manual steps — calibration with
the board on the table, then the object-absent backdrops, then the object phases —
so the operator is asked at most three times. Within a phase the table angle is the
outermost loop, the light-array angle next, then the pattern or light, then the
cameras, then the exposure bracket. Consecutive phases sweep the table in alternating
directions (and the reflectance phase alternates the array sweep per table angle), so
no full return move is made between sweeps.
"""

from __future__ import annotations

import math
import copy
from dataclasses import dataclass, field
from collections.abc import Mapping, Sequence

import numpy as np

from ..errors import ConfigError
from ..riggeometry import RigGeometry
from ..session import shot_key
from .plan import CapturePlan

__all__ = [
    "PlannedShot",
    "Stage",
    "MotionRates",
    "Estimate",
    "schedule",
    "select_cameras",
    "select_lights",
    "estimate",
    "upload_wire_bytes",
    "move_time_s",
    "expected_counts",
    "natural_displays",
    "natural_pattern_ids",
    "lamps_for_plan",
    "ArrayCoverage",
    "array_coverage",
    "require_array_coverage",
    "natural_view_note",
    "NATURAL_NEW_VIEW_REL_ERR",
]


@dataclass(frozen=True)
class PlannedShot:
    """One rig state photographed by one camera over one exposure bracket."""

    phase: str
    camera: int
    table_deg: float
    exposures_s: tuple[float, ...]
    lights_deg: float | None = None
    light: int | None = None  # reflectance: the one light on
    level: int = 0  # DMX level of the lit lights
    lights_on: tuple[int, ...] = ()  # ids lit at ``level``
    pattern: int | None = None  # shown on every display; None = blank
    object_present: bool = True

    @property
    def key(self) -> str:
        # The array angle names the shot only where it varies within a view (reflectance).
        ld = self.lights_deg if self.phase == "reflectance" else None
        return shot_key(
            self.phase,
            self.camera,
            self.table_deg,
            lights_deg=ld,
            light=self.light,
            pattern=self.pattern,
            object_present=self.object_present,
        )

    def ids(self) -> list[str]:
        return [f"{self.key}/e{i}" for i in range(len(self.exposures_s))]

    def rel_path(self, i: int) -> str:
        return f"images/{self.key}_e{i}.exr"

    @property
    def state(self) -> tuple:
        """The device state this shot needs (shots of one state differ only by camera)."""
        return (self.table_deg, self.lights_deg, self.lights_on, self.level, self.pattern, self.object_present)


@dataclass(frozen=True)
class Stage:
    """Shots that share a manual set-up: ``scene`` is ``"board"``, ``"empty"`` or ``"object"``."""

    scene: str
    shots: tuple[PlannedShot, ...]
    charuco: object = None


def select_cameras(plan: CapturePlan, geometry: RigGeometry) -> tuple[int, ...]:
    n = len(geometry.cameras)
    if plan.cameras is None:
        return tuple(range(n))
    if isinstance(plan.cameras, int):
        if plan.cameras > n:
            raise ConfigError(f"{plan.source or 'plan'}: [plan].cameras = {plan.cameras} but the rig has {n} cameras")
        return tuple(sorted({int(round(i * n / plan.cameras)) % n for i in range(plan.cameras)}))
    bad = [c for c in plan.cameras if c >= n]
    if bad:
        raise ConfigError(
            f"{plan.source or 'plan'}: [plan].cameras: index {bad} not in the rig (it has {n} cameras: 0..{n - 1})"
        )
    return tuple(plan.cameras)


def select_lights(plan: CapturePlan, geometry: RigGeometry) -> tuple[int, ...]:
    ids = [L.id for L in geometry.lights]
    ph = plan.reflectance
    if ph is None or ph.lights is None:
        return tuple(ids)
    if isinstance(ph.lights, int):
        if ph.lights > len(ids):
            raise ConfigError(
                f"{plan.source or 'plan'}: [phases.reflectance].lights = {ph.lights} but the rig has {len(ids)} lights"
            )
        return tuple(ids[int(round(i * len(ids) / ph.lights)) % len(ids)] for i in range(ph.lights))
    bad = [i for i in ph.lights if i not in ids]
    if bad:
        raise ConfigError(
            f"{plan.source or 'plan'}: [phases.reflectance].lights: id(s) {bad} not in the rig (light ids: {ids})"
        )
    return tuple(ph.lights)


def lamps_for_plan(plan: CapturePlan, geometry: RigGeometry, *, can_fit: bool) -> RigGeometry:
    """``geometry`` with the lamps the plan needs: every light's ``radius_m`` set to
    ``[phases.reflectance].lamp_radius_m`` when the plan gives one.

    ``can_fit``: the rig can take the plan's lamps itself (the simulator swaps its
    emitters); a physical rig cannot, so its TOML must already say the radius (the
    operator fits the diffusers and records them), else the capture is refused: the
    session records the lamps it was taken under.

    Raises
    ------
    ConfigError
        A rig that cannot fit the lamps and whose lights differ from the plan's radius.
    """
    r = plan.reflectance.lamp_radius_m if plan.reflectance is not None else None
    if r is None or all(L.radius_m is not None and abs(L.radius_m - r) <= 1e-6 for L in geometry.lights):
        return geometry
    if not can_fit:
        radii = sorted({L.radius_m for L in geometry.lights if L.radius_m is not None})
        have = "are points (no radius_m)" if not radii else f"have radius_m {radii} m"
        raise ConfigError(
            f"{plan.source or 'plan'}: [phases.reflectance].lamp_radius_m = {r} m but the rig's lamps {have}; "
            f"fit the lamps' diffusers and set radius_m = {r} on every [[geometry.lights]] of the rig TOML"
        )
    raw = copy.deepcopy(geometry.to_dict())
    for L in raw.get("lights", []):
        L["radius_m"] = float(r)
    return RigGeometry.from_dict(raw, where=f"{plan.source or 'plan'}: lamps of radius {r} m on the rig")


@dataclass(frozen=True, kw_only=True)
class ArrayCoverage:
    """Which one-light shots of a plan light the light array's share of the sphere (the
    directions the natural phase's displays do not cover, :mod:`opacityhull.relight.split`).

    Attributes
    ----------
    displays : names of the natural phase's displays.
    shots : (light id, array angle °, table angle °) of every one-light position.
    outside : per shot, whether any direction of the lamp (its centre, or its disc's rim
        for a lamp with area) seen from the object misses every display.
    """

    displays: tuple[str, ...]
    shots: tuple[tuple[int, float, float], ...]
    outside: tuple[bool, ...]

    @property
    def n_covering(self) -> int:
        return int(sum(self.outside))


def _lamp_cap_directions(pos: np.ndarray, centre: np.ndarray, radius_m: float | None, n_rim: int = 8) -> np.ndarray:
    """(1 + n_rim, 3) unit directions from ``centre`` to a lamp at ``pos``: its centre
    and, for a lamp with area, ``n_rim`` directions on the rim of its disc as seen."""
    d = pos - centre
    dist = float(np.linalg.norm(d))
    w = d / dist
    if not radius_m:
        return w[None]
    half = math.asin(min(1.0, radius_m / dist))
    a = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(w, a)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    phi = np.arange(n_rim) * (2.0 * math.pi / n_rim)
    rim = math.cos(half) * w[None] + math.sin(half) * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    return np.vstack([w[None], rim])


def _hits_display(display, table_deg: float, dirs: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Whether rays from ``centre`` along ``dirs`` (rig frame) meet ``display``'s rectangle
    at ``table_deg`` (the same test as the sphere split, in the rig frame)."""
    from ..camera import rig_from_object

    F = display.frame()
    if display.rotates_with_table:
        F = rig_from_object(table_deg) @ F
    Finv = np.linalg.inv(F)
    o = Finv[:3, :3] @ centre + Finv[:3, 3]
    v = dirs @ Finv[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / v[:, 2]
    x = o[0] + t * v[:, 0]
    y = o[1] + t * v[:, 1]
    w, h = display.size_m
    return np.isfinite(t) & (t > 0) & (np.abs(x) <= w / 2) & (np.abs(y) <= h / 2)


def array_coverage(plan: CapturePlan, geometry: RigGeometry) -> ArrayCoverage | None:
    """The :class:`ArrayCoverage` of a plan with both a natural and a reflectance phase
    (the model relights with the sphere split), else None. Directions are taken from the
    rig's aim point ``target_m`` on the table axis (the object's centre, as captured)."""
    if plan.natural is None or plan.reflectance is None or not geometry.lights:
        return None
    names = natural_displays(plan, geometry)
    disps = [geometry.display(n) for n in names]
    centre = np.asarray(geometry.target_m, np.float64)
    shots, outside = [], []
    for lid in select_lights(plan, geometry):
        L = geometry.light(lid)
        for ad in plan.reflectance.array_deg:
            pos = L.position_rig(ad)
            dirs = _lamp_cap_directions(np.asarray(pos, np.float64), centre, L.radius_m)
            for a in plan.table_deg:
                hit = np.zeros(len(dirs), bool)
                for d in disps:
                    hit |= _hits_display(d, a, dirs, centre)
                shots.append((int(lid), float(ad), float(a)))
                outside.append(bool(not hit.all()))
    return ArrayCoverage(displays=tuple(names), shots=tuple(shots), outside=tuple(outside))


def require_array_coverage(plan: CapturePlan, geometry: RigGeometry) -> ArrayCoverage | None:
    """:func:`array_coverage`, refusing a plan whose light array covers no direction of
    its share: every lamp, at every array and table angle, is seen inside a display, so
    the one-light images would relight nothing and the split's array share (every
    direction the displays do not cover) would be dark in every relit image.

    Raises
    ------
    ConfigError
        The light array covers no direction outside the natural phase's displays.
    """
    cov = array_coverage(plan, geometry)
    if cov is not None and cov.shots and cov.n_covering == 0:
        raise ConfigError(
            f"{plan.source or 'plan'}: [phases.reflectance] covers no direction of the light array's share: "
            f"all {len(cov.shots)} lamp positions (lights {sorted({s[0] for s in cov.shots})} x array angles "
            f"{sorted(plan.reflectance.array_deg) if plan.reflectance else []}) are seen inside the displays "
            f"{list(cov.displays)} of [phases.natural], which relight those directions; relighting splits the "
            "sphere, so the directions no display covers would stay dark — give array angles or lights "
            "outside the displays"
        )
    return cov


#: A glass relit at a new viewpoint s degrees from both captured neighbours (ULR of the
#: relit views onto the hull, true cameras): relative error against Mitsuba under uffizi
#: by s, measured by ``benchmarks/glass.py --heldout`` (benchmarks/out/glass.md). s = 0
#: is a captured viewpoint drawn by the same renderer; relit directly it is 0.36-0.39.
NATURAL_NEW_VIEW_REL_ERR = {0.0: 0.51, 3.0: 0.73, 6.0: 0.83, 9.0: 0.88}


def natural_view_note(plan: CapturePlan) -> str | None:
    """What a plan with a natural phase can relight: its captured viewpoints; a new
    viewpoint of a refracting object between them is far worse at every table spacing
    measured (:data:`NATURAL_NEW_VIEW_REL_ERR`). None for a plan without a natural phase."""
    if plan.natural is None:
        return None
    a = sorted(plan.table_deg)
    gaps = [(b - x) for x, b in zip(a, a[1:] + [a[0] + 360.0], strict=True)] if len(a) > 1 else [360.0]
    widest = max(gaps)
    between = "one table angle" if len(a) == 1 else f"table angles up to {widest:g} deg apart"
    figs = ", ".join(f"{v:.2f} at {s:g} deg" for s, v in NATURAL_NEW_VIEW_REL_ERR.items() if s > 0)
    return (
        f"{plan.source or 'plan'}: a glass captured with this plan is relit faithfully at its captured "
        f"viewpoints only ({between}); measured on sim:builtin:glass under uffizi, a new viewpoint between "
        f"captured table angles has relative error {figs} from its neighbours "
        f"({NATURAL_NEW_VIEW_REL_ERR[0.0]:.2f} at a captured one drawn the same way) — "
        "no table spacing of 3 deg or more gives a new viewpoint within 0.3 (benchmarks/out/glass.md)"
    )


def _lights_at(spec, table_deg: float) -> float:
    return table_deg if spec == "table" else float(spec)


def schedule(plan: CapturePlan, geometry: RigGeometry) -> list[Stage]:
    """The shots of ``plan`` on a rig with ``geometry``, grouped in stages, in capture order."""
    cams = select_cameras(plan, geometry)
    all_lights = tuple(L.id for L in geometry.lights)
    stages: list[Stage] = []
    sweep_dir = [1]

    def sweep(angles: Sequence[float]) -> list[float]:
        a = sorted(angles)
        if sweep_dir[0] < 0:
            a = a[::-1]
        sweep_dir[0] = -sweep_dir[0]
        return a

    def need_lights(phase: str, level: int):
        if level > 0 and not all_lights:
            raise ConfigError(
                f"{plan.source or 'plan'}: [phases.{phase}].level = {level} but the rig has no lights (set level = 0)"
            )

    def lit(phase, ph, a, exps, ld, patterns=(None,), *, object_present: bool = True) -> list[PlannedShot]:
        # every light at the phase's level (or all off), one shot per pattern and camera
        on = all_lights if ph.level else ()
        return [
            PlannedShot(
                phase,
                c,
                a,
                exps,
                lights_deg=ld,
                level=ph.level,
                lights_on=on,
                pattern=pid,
                object_present=object_present,
            )
            for pid in patterns
            for c in cams
        ]

    if plan.calibration is not None:
        ph = plan.calibration
        need_lights("calibration", ph.level)
        exps = plan.exposures("calibration")
        shots = []
        for a in sweep(ph.table_deg):
            shots += lit("calibration", ph, a, exps, ph.lights_deg if all_lights else None)
        stages.append(Stage("board", tuple(shots), charuco=ph.charuco))

    if plan.matting is not None and plan.matting.object_absent:
        ph = plan.matting
        if not geometry.displays:
            raise ConfigError(f"{plan.source or 'plan'}: [phases.matting] needs backdrop displays; the rig has none")
        exps = plan.exposures("matting")
        shots = []
        need_lights("matting", ph.level)
        for a in sweep(plan.table_deg):
            # Exactly the conditions of the object-present matting shots (same lights, same
            # array angle), so that each backdrop image is what the camera would see behind
            # the object, light spilled on the display surfaces included.
            ld = _lights_at(ph.lights_deg, a) if all_lights else None
            shots += lit("matting", ph, a, exps, ld, ph.pattern_ids, object_present=False)
        stages.append(Stage("empty", tuple(shots)))

    obj: list[PlannedShot] = []
    if plan.matting is not None:
        ph = plan.matting
        if not geometry.displays:
            raise ConfigError(f"{plan.source or 'plan'}: [phases.matting] needs backdrop displays; the rig has none")
        need_lights("matting", ph.level)
        exps = plan.exposures("matting")
        for a in sweep(plan.table_deg):
            ld = _lights_at(ph.lights_deg, a) if all_lights else None
            obj += lit("matting", ph, a, exps, ld, (*ph.pattern_ids, None))
    if plan.lightfield is not None:
        ph = plan.lightfield
        need_lights("lightfield", ph.level)
        exps = plan.exposures("lightfield")
        for a in sweep(plan.table_deg):
            obj += lit("lightfield", ph, a, exps, _lights_at(ph.lights_deg, a) if all_lights else None)
    if plan.reflectance is not None:
        ph = plan.reflectance
        if not all_lights:
            raise ConfigError(f"{plan.source or 'plan'}: [phases.reflectance] needs lights; the rig has none")
        lights = select_lights(plan, geometry)
        require_array_coverage(plan, geometry)
        exps = plan.exposures("reflectance")
        arr_dir = 1
        for a in sweep(plan.table_deg):
            arr = sorted(ph.array_deg)[::arr_dir]
            arr_dir = -arr_dir
            for ad in arr:
                for lid in lights:
                    for c in cams:
                        obj.append(
                            PlannedShot(
                                "reflectance", c, a, exps, lights_deg=ad, light=lid, level=ph.level, lights_on=(lid,)
                            )
                        )
    if plan.envmatte is not None:
        ph = plan.envmatte
        need_lights("envmatte", ph.level)
        exps = plan.exposures("envmatte")
        ids = natural_pattern_ids(plan, geometry)
        for a in sweep(plan.table_deg):
            ld = _lights_at(ph.lights_deg, a) if (all_lights and ph.level) else None
            # one illumination domain at a time: its N images, the other displays black
            for dids in ids.values():
                obj += lit("envmatte", ph, a, exps, ld, dids)
    if obj:
        stages.append(Stage("object", tuple(obj)))
    keys = [s.key for st in stages for s in st.shots]
    if len(set(keys)) != len(keys):  # pragma: no cover - a bug in the loops above, not bad input
        raise RuntimeError("schedule produced duplicate shot keys")
    return stages


def envmatte_first_id(plan: CapturePlan) -> int:
    """Pattern ids: matting 1..2K, then the natural (envmatte) images."""
    return (2 * plan.matting.patterns if plan.matting is not None else 0) + 1


def natural_displays(plan: CapturePlan, geometry: RigGeometry) -> tuple[str, ...]:
    """The illumination domains of the natural phase: its ``displays`` (checked against
    the rig), or every display of the rig. A rig without displays is a ConfigError."""
    ph = plan.envmatte
    if ph is None:
        return ()
    names = tuple(d.name for d in geometry.displays)
    where = f"{plan.source or 'plan'}: [phases.natural]"
    if not names:
        raise ConfigError(
            f"{where} needs backdrop displays to show the natural images; the rig has none "
            "(remove the phase or use a rig with displays)"
        )
    if ph.displays is None:
        return names
    bad = [d for d in ph.displays if d not in names]
    if bad:
        raise ConfigError(f"{where}.displays: {bad} not in the rig (its displays: {list(names)})")
    return tuple(ph.displays)


def natural_pattern_ids(plan: CapturePlan, geometry: RigGeometry) -> dict[str, tuple[int, ...]]:
    """Pattern ids of the natural phase per illumination domain: display i of
    :func:`natural_displays` shows image k (0-based) as id ``first + i * N + k``."""
    ph = plan.envmatte
    if ph is None:
        return {}
    first, n = envmatte_first_id(plan), ph.count
    return {d: tuple(range(first + i * n, first + (i + 1) * n)) for i, d in enumerate(natural_displays(plan, geometry))}


def expected_counts(stages: Sequence[Stage]) -> dict[str, int]:
    """Images per phase (brackets counted)."""
    out: dict[str, int] = {}
    for st in stages:
        for s in st.shots:
            out[s.phase] = out.get(s.phase, 0) + len(s.exposures_s)
    return out


# --------------------------------------------------------------------------- estimates


@dataclass(frozen=True, kw_only=True)
class MotionRates:
    """Declared (or measured) speeds of the rig's motions."""

    table_rate_deg_s: float = 30.0
    table_accel_deg_s2: float = 60.0
    array_rate_deg_s: float = 30.0
    array_accel_deg_s2: float = 60.0
    serial_bytes_s: float = 11520.0  # display controller link (115200 baud, 10 bits per byte)
    #: UPLOAD_DATA chunk size of the display driver (``[devices.backdrops].chunk_bytes``)
    display_chunk_bytes: int = 512
    #: patterns the display controller stores (its IDENTIFY ``slots=``; 64 on the OHDC-2)
    display_slots: int = 64
    #: False for video-output backdrops: patterns are drawn, nothing is uploaded
    display_uploads: bool = True

    @classmethod
    def from_devices(cls, devices: Mapping | None) -> MotionRates:
        """From the ``[devices]`` table of a rig TOML; missing values keep the defaults."""
        d = dict(devices or {})
        kw = {}
        tt = d.get("turntable") or {}
        la = d.get("light_array") or {}
        rot = la.get("rotation") if isinstance(la, Mapping) else None
        for axis, table in (("table", tt), ("array", rot)):
            if isinstance(table, Mapping):
                for key, field_ in (("max_rate_deg_s", "rate_deg_s"), ("accel_deg_s2", "accel_deg_s2")):
                    if _pos(table.get(key)):
                        kw[f"{axis}_{field_}"] = float(table[key])
        bd = d.get("backdrops") or {}
        if isinstance(bd, Mapping) and bd.get("driver") == "video":
            kw["display_uploads"] = False
        if isinstance(bd, Mapping) and _pos(bd.get("baudrate")):
            kw["serial_bytes_s"] = float(bd["baudrate"]) / 10.0
        if isinstance(bd, Mapping) and isinstance(bd.get("chunk_bytes"), int) and _pos(bd.get("chunk_bytes")):
            kw["display_chunk_bytes"] = int(bd["chunk_bytes"])
        if isinstance(bd, Mapping) and isinstance(bd.get("slots"), int) and _pos(bd.get("slots")):
            kw["display_slots"] = int(bd["slots"])
        return cls(**kw)


def _pos(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def move_time_s(delta_deg: float, rate_deg_s: float, accel_deg_s2: float) -> float:
    """Time of a trapezoidal (or triangular) move over ``|delta_deg``|."""
    d = abs(float(delta_deg))
    if d == 0:
        return 0.0
    if accel_deg_s2 <= 0:
        return d / rate_deg_s
    d_acc = rate_deg_s**2 / accel_deg_s2  # accelerating and braking together
    if d >= d_acc:
        return d / rate_deg_s + rate_deg_s / accel_deg_s2
    return 2.0 * math.sqrt(d / accel_deg_s2)


@dataclass
class Estimate:
    """What a capture will take: counts, bytes and time, per phase and in total."""

    images: dict[str, int] = field(default_factory=dict)
    shots: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    moves_s: float = 0.0
    exposure_s: float = 0.0
    overhead_s: float = 0.0
    operator_s: float = 0.0
    upload_s: float = 0.0
    uploads: int = 0  # pattern images sent to the display controller (re-uploads included)
    upload_bytes: int = 0  # bytes on the serial link for them (frames, replies, deletes)
    operator_steps: int = 0

    @property
    def total_images(self) -> int:
        return sum(self.images.values())

    @property
    def total_bytes(self) -> int:
        return sum(self.bytes.values())

    @property
    def total_s(self) -> float:
        return sum(self.seconds.values()) + self.operator_s + self.upload_s

    def to_dict(self) -> dict:
        return {
            "images": self.total_images,
            "bytes": self.total_bytes,
            "seconds": self.total_s,
            "per_phase": {
                p: {
                    "images": self.images[p],
                    "shots": self.shots[p],
                    "bytes": self.bytes[p],
                    "seconds": self.seconds[p],
                }
                for p in self.images
            },
            "breakdown_s": {
                "moves": self.moves_s,
                "exposure": self.exposure_s,
                "overhead": self.overhead_s,
                "operator": self.operator_s,
                "pattern_upload": self.upload_s,
            },
            "pattern_uploads": {"count": self.uploads, "bytes": self.upload_bytes, "seconds": self.upload_s},
            "operator_steps": self.operator_steps,
        }


def image_bytes(width: int, height: int, *, half: bool = False, channels: int = 3) -> int:
    """Upper estimate of one EXR image on disk: uncompressed pixels plus a header.

    ZIP compression of noisy sensor data saves little, and the free-disk check wants
    an upper bound."""
    return int(width * height * channels * (2 if half else 4) + 1024)


def estimate(
    plan: CapturePlan,
    geometry: RigGeometry,
    rates: MotionRates | None = None,
    stages: Sequence[Stage] | None = None,
    *,
    upload_patterns: bool = True,
) -> Estimate:
    """Counts, bytes and time of a capture, walking the schedule like the runner does."""
    rates = rates or MotionRates()
    stages = list(stages) if stages is not None else schedule(plan, geometry)
    est = Estimate()
    tm = plan.timing
    table, array = 0.0, 0.0
    prev_state = None
    for st in stages:
        est.operator_steps += 1 if st.scene != "empty" else 2
        for s in st.shots:
            p = s.phase
            t = 0.0
            if s.state != prev_state:
                dt = move_time_s(_ang(s.table_deg - table), rates.table_rate_deg_s, rates.table_accel_deg_s2)
                da = 0.0
                if s.lights_deg is not None:
                    da = move_time_s(_ang(s.lights_deg - array), rates.array_rate_deg_s, rates.array_accel_deg_s2)
                    array = s.lights_deg
                table = s.table_deg
                mv = max(dt, da)  # the two axes move at the same time
                est.moves_s += mv
                t += mv + tm.settle_s
                prev_state = s.state
            cam = geometry.cameras[s.camera]
            n = len(s.exposures_s)
            t += sum(s.exposures_s) + n * tm.per_image_s
            est.exposure_s += sum(s.exposures_s)
            est.overhead_s += n * tm.per_image_s
            est.images[p] = est.images.get(p, 0) + n
            est.shots[p] = est.shots.get(p, 0) + 1
            est.bytes[p] = est.bytes.get(p, 0) + n * image_bytes(cam.width, cam.height, half=plan.half_float)
            est.seconds[p] = est.seconds.get(p, 0.0) + t
    est.operator_s = est.operator_steps * tm.operator_s
    if upload_patterns and rates.display_uploads and geometry.displays:
        est.uploads, est.upload_bytes = _pattern_uploads(plan, geometry, stages, rates)
        est.upload_s = est.upload_bytes / rates.serial_bytes_s
    return est


def upload_wire_bytes(width: int, height: int, *, chunk_bytes: int = 512, escape_rate: float = 2 / 256) -> float:
    """Bytes on the display link, both directions, to upload one ``width`` x ``height``
    RGB8 pattern the way :meth:`opacityhull.rigs.backdrops.SerialBackdrops.upload` does it.

    PATTERN_INFO (answered "no such pattern"), UPLOAD_BEGIN, one UPLOAD_DATA per chunk,
    UPLOAD_END, each frame and its reply as :func:`~opacityhull.rigs.display_protocol.encode_frame`
    puts them on the wire. Image bytes equal to the flag or escape byte are sent as two:
    ``escape_rate`` is their expected fraction (2/256 for uniformly distributed bytes).
    """
    from ..rigs import display_protocol as dp

    def frame(msg: tuple[int, bytes]) -> int:
        return len(dp.encode_frame(1, *msg))

    nbytes = int(width) * int(height) * 3
    pid = 1  # a slot id whose bytes need no escaping
    n = frame(dp.pattern_info(pid)) + frame(dp.nak(dp.CMD_PATTERN_INFO, dp.NAK_NO_PATTERN))
    n += frame(dp.upload_begin(pid, width, height)) + frame(dp.ack(dp.CMD_UPLOAD_BEGIN))
    for off, k in dp.pattern_chunks(nbytes, chunk_bytes):
        n += frame(dp.upload_data(pid, off, bytes(k))) + frame(dp.ack(dp.CMD_UPLOAD_DATA, bytes(4)))
    n += frame(dp.upload_end(pid, 0)) + frame(dp.ack(dp.CMD_UPLOAD_END))
    return n + escape_rate * nbytes


def _pattern_uploads(
    plan: CapturePlan, geometry: RigGeometry, stages: Sequence[Stage], rates: MotionRates
) -> tuple[int, int]:
    """Uploads and link bytes of the runner's least-recently-used pattern store
    (``PatternSlots`` in pattern_cache.py) over the schedule, on an empty controller.

    Every display has its own slot per pattern id, except that identical images share
    one: the black a natural pattern shows on the displays it does not light. Once the
    patterns of a table angle do not fit in ``rates.display_slots``, the cyclic sweep
    evicts each before it is shown again, so every table angle re-uploads them all
    (about N x displays + 1 for the natural phase)."""
    from collections import OrderedDict

    from ..rigs import display_protocol as dp

    lit = {pid: d for d, ids in natural_pattern_ids(plan, geometry).items() for pid in ids}
    res = [tuple(int(v) for v in d.resolution) for d in geometry.displays]
    cost = {r: upload_wire_bytes(*r, chunk_bytes=rates.display_chunk_bytes) for r in set(res)}
    delete_b = len(dp.encode_frame(1, *dp.delete(1))) + len(dp.encode_frame(1, *dp.ack(dp.CMD_DELETE)))
    cap = max(1, int(rates.display_slots))
    stored: OrderedDict = OrderedDict()
    uploads, deletes, nbytes = 0, 0, 0.0
    prev = None
    for st in stages:
        for s in st.shots:
            if s.pattern is None or s.state == prev:
                continue
            prev = s.state
            need = []
            for i, d in enumerate(geometry.displays):
                black = s.pattern in lit and lit[s.pattern] != d.name
                need.append((("black", res[i]) if black else (s.pattern, i), res[i]))
            keep = {k for k, _ in need}
            for k, r in need:
                if k in stored:
                    stored.move_to_end(k)
                    continue
                while len(stored) >= cap:
                    victim = next((x for x in stored if x not in keep), None)
                    if victim is None:  # the runner refuses this shot with a ConfigError
                        break
                    del stored[victim]
                    deletes += 1
                stored[k] = None
                uploads += 1
                nbytes += cost[r]
    return uploads, int(round(nbytes + deletes * delete_b))


def _ang(d: float) -> float:
    """Absolute moves: the table goes the way the controller goes (no wrap-around)."""
    return float(d)


def human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1000.0
    return f"{n:.1f} TB"  # pragma: no cover


def human_seconds(s: float) -> str:
    s = float(s)
    if s < 60:
        return f"{s:.1f} s"
    m, sec = divmod(int(round(s)), 60)
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min" if h else f"{m} min {sec:02d} s"
