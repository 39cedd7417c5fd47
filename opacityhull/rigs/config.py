"""The rig TOML: devices (this module) and geometry (:mod:`opacityhull.riggeometry`).

:func:`load_rig_config` parses a rig file into a frozen :class:`RigConfig`. Every
problem raises :class:`~opacityhull.errors.ConfigError` naming the file and the key
(``rig.toml: devices.light_array.channels: no DMX channel for light 2``), and the
devices are checked against the geometry: a DMX channel per light, a controller
output per display, the cameras in the same names and order as ``geometry.cameras``.

URLs: a device path, ``socket://HOST:PORT``, ``loop://`` or ``emulator:KIND[#tag]``
(``KIND`` = ``grbl`` | ``enttec`` | ``display`` | ``mdc``, resolved by
:func:`opacityhull.rigs.emulators.launch.start_emulators`). Identical URL strings name
the same port: the turntable and the light-array rotation on one URL are two axes of
one GRBL controller.

The schema is documented in the notes shared by the rig engineers (RIGTOML) and in
``examples/rig-emulated.toml``.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from collections.abc import Mapping

from ..errors import ConfigError, InputError
from ..riggeometry import RigGeometry
from ..tomlio import TomlContext, read_toml
from .backdrops import DISPLAY_SERIAL
from .lights import DMX_SERIAL
from .motion import GRBL_SERIAL
from .panels import MDC_SERIAL, PanelSettings
from .transport import SerialSettings, check_url

log = logging.getLogger(__name__)

__all__ = [
    "PortConfig",
    "AxisConfig",
    "LightArrayConfig",
    "BackdropsConfig",
    "PanelConfig",
    "CameraConfig",
    "RigConfig",
    "load_rig_config",
    "parse_rig_config",
    "parse_emulator_url",
    "emulator_url_faults",
    "EMULATOR_KINDS",
    "CAMERA_DRIVERS",
    "emulated_axis",
]

EMULATOR_KINDS = ("grbl", "enttec", "display", "mdc")
BACKDROP_DRIVERS = ("ohdc2", "video")
CAMERA_DRIVERS = ("opencv", "directory", "sim")
GRBL_AXES = ("X", "Y", "Z", "A", "B", "C")


def emulated_axis(axis: str, *, max_rate_deg_s: float, accel_deg_s2: float | None = None) -> dict[str, Any]:
    """A ``[devices.turntable]`` (or ``[devices.light_array.rotation]``) table driving
    the GRBL emulator's ``axis`` at 80 steps/degree with a 2 s reply timeout; without
    ``accel_deg_s2`` the emulator's default acceleration applies."""
    table: dict[str, Any] = {
        "url": "emulator:grbl",
        "axis": axis,
        "steps_per_deg": 80.0,
        "max_rate_deg_s": max_rate_deg_s,
    }
    if accel_deg_s2 is not None:
        table["accel_deg_s2"] = accel_deg_s2
    table["timeout_s"] = 2.0
    return table


_AXIS_KEYS = {
    "url",
    "axis",
    "steps_per_deg",
    "max_rate_deg_s",
    "accel_deg_s2",
    "backlash_deg",
    "soft_limits_deg",
    "timeout_s",
    "baudrate",
}
_LIGHT_KEYS = {"url", "timeout_s", "baudrate", "rotation", "channels"}
_BACKDROP_KEYS = {"url", "timeout_s", "baudrate", "outputs", "retries", "chunk_bytes", "slots", "driver"}
_VIDEO_KEYS = {"driver", "monitors", "response_ms", "x_display"}
_PANEL_KEYS = {
    "url",
    "id",
    "timeout_s",
    "baudrate",
    "retries",
    "input",
    "brightness",
    "contrast",
    "backlight",
    "picture_mode",
    "dynamic_contrast_cmd",
}
_CAMERA_COMMON = {"name", "driver", "device"}
_CAMERA_OPTIONS = {
    "opencv": {"fourcc", "timeout_s", "linearize", "white_level", "backend", "exposure_control", "discard_frames"},
    "directory": {"pattern", "timeout_s", "settle_s", "trigger", "linearize", "white_level"},
    "sim": None,  # options belong to the simulator
}


def parse_emulator_url(url: str) -> tuple[str, str] | None:
    """``"emulator:grbl#a"`` → ``("grbl", "a")``; None for other URLs. A query of faults
    (``emulator:grbl#a?fault=babble:5000``, see :func:`emulator_url_faults`) is not part
    of the kind or the tag."""
    if not isinstance(url, str) or not url.startswith("emulator:"):
        return None
    rest = url[len("emulator:") :].partition("?")[0]
    kind, _, tag = rest.partition("#")
    return kind, tag


def emulator_url_faults(url: str) -> list[str]:
    """The ``fault=KIND[:ARGS]`` entries of an ``emulator:`` URL's query, in order
    (``emulator:grbl?fault=garble:2&fault=delay:0.1`` → ``["garble:2", "delay:0.1"]``).
    Raises :class:`ConfigError` for another query key."""
    if not isinstance(url, str) or "?" not in url:
        return []
    out = []
    for item in url.partition("?")[2].split("&"):
        if not item:
            continue
        key, eq, val = item.partition("=")
        if key != "fault" or not eq:
            raise ConfigError(
                f"{url!r}: unknown query {item!r} (expected fault=KIND[:ARGS], see docs/emulator-faults.md)"
            )
        out.append(val)
    return out


def _slot_map(ctx, key: str, table: Mapping, owners: list, owner_of, *, slots, unknown, bad, used, missing) -> dict:
    """``table`` (TOML key -> device slot, e.g. light id -> DMX channel) checked: every
    key names one of ``owners`` (``owner_of`` parses it), every slot is an integer in
    ``slots`` (lo, hi) used once, every owner has one. The messages are templates over
    ``owner``, ``owners``, ``value``, ``other`` (the owner already on that slot), ``i``."""
    lo, hi = slots
    out: dict = {}
    for k, v in table.items():
        owner = owner_of(k)
        if owner not in owners:
            raise ctx.err(f"{key}.{k}", unknown.format(owner=owner, owners=owners))
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ctx.err(f"{key}.{k}", bad.format(value=v))
        if v in out.values():
            other = [o for o, s in out.items() if s == v][0]
            raise ctx.err(f"{key}.{k}", used.format(value=v, other=other))
        out[owner] = v
    for i, owner in enumerate(owners):
        if owner not in out:
            raise ctx.err(key, missing.format(owner=owner, i=i))
    return out


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True, kw_only=True)
class PortConfig:
    """What every serial device of the rig has: its name, URL, serial settings (the
    table's ``timeout_s`` and ``baudrate``, and the backdrops' ``retries``; the rest are
    the driver's defaults) and the TOML key path of its table (for messages)."""

    name: str
    url: str
    serial: SerialSettings
    key: str = ""


@dataclass(frozen=True, kw_only=True)
class AxisConfig(PortConfig):
    """A GRBL axis: the turntable or the light-array rotation."""

    serial: SerialSettings = GRBL_SERIAL
    axis: str = "X"
    steps_per_deg: float = 80.0
    max_rate_deg_s: float = 30.0
    accel_deg_s2: float = 60.0
    backlash_deg: float = 0.0
    soft_limits_deg: tuple[float, float] | None = None


@dataclass(frozen=True, kw_only=True)
class LightArrayConfig(PortConfig):
    """Enttec DMX USB Pro and the light id → DMX channel map; the rotation axis if any."""

    channels: tuple[tuple[int, int], ...]
    rotation: AxisConfig | None = None
    serial: SerialSettings = DMX_SERIAL
    key: str = "devices.light_array"

    @property
    def channel_map(self) -> dict[int, int]:
        """Light id → DMX channel (1-based)."""
        return dict(self.channels)


@dataclass(frozen=True, kw_only=True)
class BackdropsConfig(PortConfig):
    """The backdrops: an OHDC-2 display controller (``driver = "ohdc2"``: the display
    name → output map) or monitors of this computer (``driver = "video"``: display name →
    monitor name, the panels' response time; ``url`` is then ``video:X_DISPLAY``)."""

    outputs: tuple[tuple[str, int], ...] = ()
    serial: SerialSettings = DISPLAY_SERIAL
    chunk_bytes: int = 512
    key: str = "devices.backdrops"
    driver: str = "ohdc2"
    monitors: tuple[tuple[str, str], ...] = ()
    response_ms: float = 0.0
    x_display: str | None = None

    @property
    def output_map(self) -> dict[str, int]:
        return dict(self.outputs)

    @property
    def monitor_map(self) -> dict[str, str]:
        return dict(self.monitors)


@dataclass(frozen=True, kw_only=True)
class PanelConfig(PortConfig):
    """``[devices.panels.DISPLAY]``: the RS-232 (Samsung MDC) control port of a display
    shown through a video output."""

    display: str
    display_id: int
    settings: PanelSettings
    serial: SerialSettings = MDC_SERIAL


@dataclass(frozen=True)
class CameraConfig:
    """One ``[[devices.cameras]]`` entry; ``width``/``height`` come from the geometry."""

    name: str
    driver: str
    device: Any = None
    width: int = 0
    height: int = 0
    options: tuple[tuple[str, Any], ...] = ()
    key: str = ""

    def option(self, key: str, default=None):
        return dict(self.options).get(key, default)


@dataclass(frozen=True)
class RigConfig:
    """A parsed rig TOML."""

    name: str
    turntable: AxisConfig
    geometry: RigGeometry
    light_array: LightArrayConfig | None = None
    backdrops: BackdropsConfig | None = None
    cameras: tuple[CameraConfig, ...] = ()
    panels: tuple[PanelConfig, ...] = ()
    raw: dict = field(default_factory=dict, compare=False, repr=False)
    source: str = "<rig config>"

    # ---- queries
    def axes(self) -> list[AxisConfig]:
        out = [self.turntable]
        if self.light_array is not None and self.light_array.rotation is not None:
            out.append(self.light_array.rotation)
        return out

    def device_urls(self) -> dict[str, str]:
        """Device name → URL (serial devices only; cameras have none)."""
        out = {self.turntable.name: self.turntable.url}
        if self.light_array is not None:
            out[self.light_array.name] = self.light_array.url
            if self.light_array.rotation is not None:
                out[self.light_array.rotation.name] = self.light_array.rotation.url
        if self.backdrops is not None and self.backdrops.driver != "video":
            out[self.backdrops.name] = self.backdrops.url
        for p in self.panels:
            out[p.name] = p.url
        return out

    def grbl_ports(self) -> dict[str, list[AxisConfig]]:
        """URL → the axes on that GRBL controller (one controller per distinct URL)."""
        out: dict[str, list[AxisConfig]] = {}
        for ax in self.axes():
            out.setdefault(ax.url, []).append(ax)
        return out

    def emulated(self) -> bool:
        return any(parse_emulator_url(u) for u in self.device_urls().values())

    # ---- rewriting
    def with_urls(self, mapping: Mapping[str, str]) -> RigConfig:
        """A copy with every URL in ``mapping`` replaced (e.g. ``emulator:grbl`` → ``/dev/pts/4``)."""

        def sub(u: str) -> str:
            return mapping.get(u, u)

        raw = copy.deepcopy(self.raw)
        dev = raw.get("devices", {})
        for k in ("turntable", "light_array", "backdrops"):
            if isinstance(dev.get(k), dict) and "url" in dev[k]:
                dev[k]["url"] = sub(dev[k]["url"])
        la = dev.get("light_array")
        if isinstance(la, dict) and isinstance(la.get("rotation"), dict) and "url" in la["rotation"]:
            la["rotation"]["url"] = sub(la["rotation"]["url"])
        la_cfg = self.light_array
        if la_cfg is not None:
            rot = la_cfg.rotation
            la_cfg = replace(
                la_cfg, url=sub(la_cfg.url), rotation=None if rot is None else replace(rot, url=sub(rot.url))
            )
        bd = self.backdrops if self.backdrops is None else replace(self.backdrops, url=sub(self.backdrops.url))
        for t in (dev.get("panels") or {}).values():
            if isinstance(t, dict) and "url" in t:
                t["url"] = sub(t["url"])
        return replace(
            self,
            turntable=replace(self.turntable, url=sub(self.turntable.url)),
            light_array=la_cfg,
            backdrops=bd,
            panels=tuple(replace(p, url=sub(p.url)) for p in self.panels),
            raw=raw,
        )

    def to_dict(self) -> dict:
        """The TOML content (``rig``, ``devices``, ``geometry`` tables)."""
        return copy.deepcopy(self.raw)

    def to_toml(self) -> str:
        from ..tomlio import toml_dumps

        return toml_dumps(self.to_dict())

    def write(self, path) -> Path:
        """Write :meth:`to_toml` atomically."""
        from ..imageio import atomic_path

        path = Path(path)
        with atomic_path(path) as tmp:
            tmp.write_text(self.to_toml())
        return path


# --------------------------------------------------------------------------- parsing helpers


class _Ctx(TomlContext):
    """The shared typed getters (errors are ConfigError naming the file and key), plus
    device URLs."""

    def __init__(self, source: str):
        super().__init__(source, error=ConfigError)

    def url(self, key: str, d: Mapping, kind: str) -> str:
        if "url" not in d:
            raise self.err(key, "missing key 'url'")
        u = d["url"]
        check_url(u, where=f"{self.source}: {key}.url")
        em = parse_emulator_url(u)
        if em is not None:
            k, _tag = em
            if k not in EMULATOR_KINDS:
                raise self.err(
                    f"{key}.url",
                    f"unknown emulator kind {k!r} in {u!r} (expected emulator:KIND[#tag] "
                    f"with KIND one of {list(EMULATOR_KINDS)})",
                )
            if k != kind:
                raise self.err(
                    f"{key}.url", f"{u!r} emulates a {k} device, but this device is a {kind} (use emulator:{kind})"
                )
            from .emulators.faults import parse_fault

            try:
                for f in emulator_url_faults(u):
                    parse_fault(f)
            except ConfigError as e:
                raise self.err(f"{key}.url", str(e)) from None
        return u


def _serial(ctx: _Ctx, key: str, d: Mapping, defaults: SerialSettings, *, retries: bool = False) -> SerialSettings:
    """The device table's ``timeout_s``, ``baudrate`` (and, with ``retries``, ``retries``)
    over the driver's ``defaults``."""
    values: dict[str, Any] = {
        "timeout_s": ctx.num(key, d, "timeout_s", defaults.timeout_s, positive=True),
        "baudrate": ctx.int_(key, d, "baudrate", defaults.baudrate, 300, 4_000_000),
    }
    if retries:
        values["retries"] = ctx.int_(key, d, "retries", defaults.retries, 0, 100)
    return replace(defaults, **values)


def _axis(ctx: _Ctx, key: str, name: str, d, defaults: AxisConfig | None = None) -> AxisConfig:
    d = ctx.table(key, d)
    ctx.keys(key, d, _AXIS_KEYS)
    url = ctx.url(key, d, "grbl")
    axis = ctx.str_(key, d, "axis", "X")
    if axis.upper() not in GRBL_AXES:
        raise ctx.err(f"{key}.axis", f"expected a GRBL axis letter {list(GRBL_AXES)}, got {axis!r}")
    limits = d.get("soft_limits_deg")
    if limits is not None:
        if (
            not isinstance(limits, list)
            or len(limits) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in limits)
            or not limits[0] < limits[1]
        ):
            raise ctx.err(f"{key}.soft_limits_deg", f"expected [min_deg, max_deg] with min < max, got {limits!r}")
        limits = (float(limits[0]), float(limits[1]))
    return AxisConfig(
        name=name,
        url=url,
        axis=axis.upper(),
        steps_per_deg=ctx.num(key, d, "steps_per_deg", 80.0, positive=True),
        max_rate_deg_s=ctx.num(key, d, "max_rate_deg_s", 30.0, positive=True),
        accel_deg_s2=ctx.num(key, d, "accel_deg_s2", 60.0, positive=True),
        backlash_deg=ctx.num(key, d, "backlash_deg", 0.0, nonneg=True),
        soft_limits_deg=limits,
        serial=_serial(ctx, key, d, GRBL_SERIAL),
        key=key,
    )


# --------------------------------------------------------------------------- entry points


def load_rig_config(path) -> RigConfig:
    """Parse a rig TOML file; :class:`ConfigError` names the file and key on any problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"rig config {path} not found")
    data = read_toml(path, error=ConfigError, what="rig TOML")
    return parse_rig_config(data, source=str(path), base_dir=path.parent)


def parse_rig_config(data: Mapping[str, Any], *, source: str = "<rig config>", base_dir=None) -> RigConfig:
    """Parse the content of a rig TOML (see :func:`load_rig_config`).

    ``base_dir`` resolves relative folders of ``driver = "directory"`` cameras.
    """
    ctx = _Ctx(source)
    data = ctx.table("(top level)", data)
    ctx.keys("(top level)", data, {"rig", "devices", "geometry"})
    raw = copy.deepcopy(dict(data))
    rig = ctx.table("rig", data.get("rig", {}))
    ctx.keys("rig", rig, {"name", "description"})
    name = ctx.str_("rig", rig, "name", Path(source).stem if source != "<rig config>" else "rig")
    if "geometry" not in data:
        raise ctx.err("geometry", "missing [geometry] table (cameras, lights, displays)")
    geometry = RigGeometry.from_dict(data["geometry"], where=f"{source}: geometry")
    if "devices" not in data:
        raise ctx.err("devices", "missing [devices] table")
    dev = ctx.table("devices", data["devices"])
    ctx.keys("devices", dev, {"turntable", "light_array", "backdrops", "cameras", "panels"})

    # ---- turntable
    if "turntable" not in dev:
        raise ctx.err("devices", "missing [devices.turntable]")
    turntable = _axis(ctx, "devices.turntable", "turntable", dev["turntable"])

    # ---- light array
    light_array = None
    light_ids = [L.id for L in geometry.lights]
    if "light_array" in dev:
        key = "devices.light_array"
        la = ctx.table(key, dev["light_array"])
        ctx.keys(key, la, _LIGHT_KEYS)
        url = ctx.url(key, la, "enttec")
        if "channels" not in la:
            raise ctx.err(key, "missing [devices.light_array.channels] (light id = DMX channel)")
        ch_key = f"{key}.channels"

        def light_id(k: str) -> int:
            try:
                return int(k)
            except ValueError:
                raise ctx.err(ch_key, f"key {k!r} is not a light id (an integer)") from None

        channels = _slot_map(
            ctx,
            ch_key,
            ctx.table(ch_key, la["channels"]),
            light_ids,
            light_id,
            slots=(1, 512),
            unknown="no light with id {owner} in geometry.lights (ids: {owners})",
            bad="expected a DMX channel 1..512, got {value!r}",
            used="DMX channel {value} is already used by light {other}",
            missing="no DMX channel for light {owner} (geometry.lights[{i}]); add '{owner} = <channel>'",
        )
        rotation = None
        if "rotation" in la:
            rotation = _axis(ctx, f"{key}.rotation", "light_array.rotation", la["rotation"])
        light_array = LightArrayConfig(
            name="light_array",
            url=url,
            channels=tuple(sorted(channels.items())),
            rotation=rotation,
            serial=_serial(ctx, key, la, DMX_SERIAL),
            key=key,
        )
    elif light_ids:
        raise ctx.err(
            "devices",
            f"geometry.lights has {len(light_ids)} light(s) but there is no [devices.light_array] to switch them",
        )

    # ---- backdrops
    backdrops = None
    display_names = [d.name for d in geometry.displays]
    key = "devices.backdrops"
    bd: Mapping = {}
    driver = "ohdc2"
    if "backdrops" in dev:
        bd = ctx.table(key, dev["backdrops"])
        driver = ctx.str_(key, bd, "driver", "ohdc2")
        if driver not in BACKDROP_DRIVERS:
            raise ctx.err(f"{key}.driver", f"expected one of {list(BACKDROP_DRIVERS)}, got {driver!r}")
    if "backdrops" in dev and driver == "video":
        ctx.keys(key, bd, _VIDEO_KEYS)
        if "monitors" not in bd:
            raise ctx.err(key, "missing [devices.backdrops.monitors] (display name = monitor name, see `rig monitors`)")
        mon_key = f"{key}.monitors"
        mons = ctx.table(mon_key, bd["monitors"])
        for k, v in mons.items():
            if k not in display_names:
                raise ctx.err(f"{mon_key}.{k}", f"no display named {k!r} in geometry.displays (names: {display_names})")
            if not isinstance(v, str) or not v:
                raise ctx.err(f"{mon_key}.{k}", f"expected a monitor name such as 'HDMI-1', got {v!r}")
        for i, n in enumerate(display_names):
            if n not in mons:
                raise ctx.err(mon_key, f"no monitor for display {n!r} (geometry.displays[{i}]); add '{n} = \"HDMI-1\"'")
        if len(set(mons.values())) != len(mons):
            raise ctx.err(mon_key, f"two displays on one monitor: {dict(mons)}")
        xd = bd.get("x_display")
        if xd is not None and not isinstance(xd, str):
            raise ctx.err(f"{key}.x_display", f"expected an X display name such as ':0', got {xd!r}")
        response_ms = ctx.num(key, bd, "response_ms", 10.0, nonneg=True)
        if response_ms > 10_000:
            raise ctx.err(
                f"{key}.response_ms", f"expected the panel's response time in ms (< 10000), got {response_ms}"
            )
        backdrops = BackdropsConfig(
            name="backdrops",
            url=f"video:{xd or ''}",
            serial=DISPLAY_SERIAL,
            key=key,
            driver="video",
            monitors=tuple((n, str(mons[n])) for n in display_names),
            response_ms=response_ms,
            x_display=xd,
        )
    elif "backdrops" in dev:
        ctx.keys(key, bd, _BACKDROP_KEYS)
        url = ctx.url(key, bd, "display")
        # the controller's pattern store: only `capture --dry-run` reads it (it prices the
        # re-uploads); the runner asks the controller itself (IDENTIFY slots=)
        ctx.int_(key, bd, "slots", 64, 1, 65535)
        if "outputs" not in bd:
            raise ctx.err(key, "missing [devices.backdrops.outputs] (display name = controller output)")
        out_key = f"{key}.outputs"
        outputs = _slot_map(
            ctx,
            out_key,
            ctx.table(out_key, bd["outputs"]),
            display_names,
            str,
            slots=(0, 254),
            unknown="no display named {owner!r} in geometry.displays (names: {owners})",
            bad="expected a controller output index 0..254, got {value!r}",
            used="output {value} is already used by display {other!r}",
            missing="no controller output for display {owner!r} (geometry.displays[{i}]); add '{owner} = <output>'",
        )
        backdrops = BackdropsConfig(
            name="backdrops",
            url=url,
            outputs=tuple((n, outputs[n]) for n in display_names),
            serial=_serial(ctx, key, bd, DISPLAY_SERIAL, retries=True),
            chunk_bytes=ctx.int_(key, bd, "chunk_bytes", 512, 1, 1024),
            key=key,
        )
    elif display_names:
        raise ctx.err(
            "devices",
            f"geometry.displays has {len(display_names)} display(s) but there is no [devices.backdrops] to drive them",
        )

    # ---- the panels' control ports (video-output backdrops)
    panels: list[PanelConfig] = []
    if "panels" in dev:
        if backdrops is None or backdrops.driver != "video":
            raise ctx.err(
                "devices.panels",
                'panel control ports go with video-output backdrops ([devices.backdrops] driver = "video"); an '
                "OHDC-2 controller drives its panels itself",
            )
        ptab = ctx.table("devices.panels", dev["panels"])
        for disp, t in ptab.items():
            pkey = f"devices.panels.{disp}"
            if disp not in display_names:
                raise ctx.err(pkey, f"no display named {disp!r} in geometry.displays (names: {display_names})")
            t = ctx.table(pkey, t)
            ctx.keys(pkey, t, _PANEL_KEYS)
            purl = ctx.url(pkey, t, "mdc")
            if "id" not in t:
                raise ctx.err(pkey, "missing key 'id' (the panel's MDC display id, set in its menu)")
            from .mdc_protocol import check_display_id

            try:
                pid = check_display_id(t["id"], where=f"{ctx.source}: {pkey}.id")
            except InputError as e:
                raise ConfigError(str(e)) from None
            pm = t.get("picture_mode")
            if pm is not None:
                if not (isinstance(pm, list) and len(pm) == 2):
                    raise ctx.err(f"{pkey}.picture_mode", f"expected [command, value] bytes, got {pm!r}")
                pm = (pm[0], pm[1])
            try:
                settings = PanelSettings(
                    input=ctx.str_(pkey, t, "input", "hdmi1"),
                    brightness=t.get("brightness", 100),
                    contrast=t.get("contrast", 100),
                    backlight=t.get("backlight"),
                    picture_mode=pm,
                    dynamic_contrast_cmd=t.get("dynamic_contrast_cmd"),
                )
            except ConfigError as e:
                raise ctx.err(pkey, str(e)) from None
            panels.append(
                PanelConfig(
                    name=f"panels.{disp}",
                    url=purl,
                    key=pkey,
                    display=disp,
                    display_id=pid,
                    settings=settings,
                    serial=_serial(ctx, pkey, t, MDC_SERIAL, retries=True),
                )
            )

    # ---- cameras
    cameras: list[CameraConfig] = []
    raw_cams = dev.get("cameras", [])
    if not isinstance(raw_cams, list):
        raise ctx.err("devices.cameras", "expected an array of tables [[devices.cameras]]")
    geo_names = [c.name for c in geometry.cameras]
    seen: dict[str, int] = {}
    for i, c in enumerate(raw_cams):
        key = f"devices.cameras[{i}]"
        c = ctx.table(key, c)
        cname = ctx.str_(key, c, "name")
        if cname in seen:
            raise ctx.err(f"{key}.name", f"duplicate camera name {cname!r} (also devices.cameras[{seen[cname]}])")
        seen[cname] = i
        driver = ctx.str_(key, c, "driver")
        if driver not in CAMERA_DRIVERS:
            raise ctx.err(f"{key}.driver", f"unknown camera driver {driver!r} (one of {list(CAMERA_DRIVERS)})")
        allowed = _CAMERA_OPTIONS[driver]
        if allowed is not None:
            ctx.keys(key, c, _CAMERA_COMMON | allowed)
        device = c.get("device")
        if driver == "opencv":
            if device is None or isinstance(device, bool) or not isinstance(device, (int, str)):
                raise ctx.err(f"{key}.device", f"expected a device index or path for an opencv camera, got {device!r}")
        elif driver == "directory":
            if not isinstance(device, str) or not device:
                raise ctx.err(f"{key}.device", f"expected the folder the camera writes into, got {device!r}")
            p = Path(device).expanduser()
            if not p.is_absolute() and base_dir is not None:
                p = Path(base_dir) / p
            device = str(p)
        opts = {k: v for k, v in c.items() if k not in _CAMERA_COMMON}
        for k in ("timeout_s", "settle_s", "white_level"):
            if k in opts:
                ctx.num(key, opts, k, positive=True)
        if "linearize" in opts and opts["linearize"] not in ("srgb", "none"):
            raise ctx.err(f"{key}.linearize", f"expected 'srgb' or 'none', got {opts['linearize']!r}")
        if "exposure_control" in opts and not isinstance(opts["exposure_control"], bool):
            raise ctx.err(f"{key}.exposure_control", f"expected true or false, got {opts['exposure_control']!r}")
        if "trigger" in opts and (
            not isinstance(opts["trigger"], list)
            or not all(isinstance(a, str) for a in opts["trigger"])
            or not opts["trigger"]
        ):
            raise ctx.err(f"{key}.trigger", f"expected a command as a list of strings, got {opts['trigger']!r}")
        if "pattern" in opts and not isinstance(opts["pattern"], str):
            raise ctx.err(f"{key}.pattern", f"expected a glob string, got {opts['pattern']!r}")
        spec = geometry.cameras[i] if i < len(geometry.cameras) else None
        cameras.append(
            CameraConfig(
                name=cname,
                driver=driver,
                device=device,
                width=spec.width if spec else 0,
                height=spec.height if spec else 0,
                options=tuple(sorted(opts.items())),
                key=key,
            )
        )
    if raw_cams:
        names = [c.name for c in cameras]
        if names != geo_names:
            missing = [n for n in geo_names if n not in names]
            extra = [n for n in names if n not in geo_names]
            why = []
            if missing:
                why.append(f"missing {missing}")
            if extra:
                why.append(f"not in geometry.cameras: {extra}")
            if not why:
                why.append("same names in a different order")
            raise ctx.err(
                "devices.cameras",
                f"camera names {names} must match geometry.cameras {geo_names} in name and order ({'; '.join(why)})",
            )

    # ---- ports shared between devices
    kinds: dict[str, tuple[str, str]] = {}  # url -> (kind, key)
    entries: list[tuple[str, str, str, AxisConfig | LightArrayConfig | BackdropsConfig | PanelConfig]] = [
        (turntable.url, "grbl", turntable.key, turntable)
    ]
    if light_array is not None:
        entries.append((light_array.url, "enttec", light_array.key, light_array))
        if light_array.rotation is not None:
            r = light_array.rotation
            entries.append((r.url, "grbl", r.key, r))
    if backdrops is not None and backdrops.driver != "video":
        entries.append((backdrops.url, "display", backdrops.key, backdrops))
    for pc in panels:
        entries.append((pc.url, "mdc", pc.key, pc))
    axes_on: dict[str, AxisConfig] = {}
    for url, kind, key, obj in entries:
        if url in kinds and kinds[url][0] != kind:
            raise ctx.err(
                f"{key}.url",
                f"{url!r} is also {kinds[url][1]}.url (a {kinds[url][0]} device); one port "
                f"cannot be a {kind} device too",
            )
        if url in kinds and kind != "grbl":
            raise ctx.err(f"{key}.url", f"{url!r} is also {kinds[url][1]}.url; give each device its own port")
        kinds.setdefault(url, (kind, key))
        if isinstance(obj, AxisConfig):
            prev = axes_on.get(url + "|" + obj.axis)
            if prev is not None:
                raise ctx.err(
                    f"{key}.axis",
                    f"axis {obj.axis} of the controller at {url!r} is already {prev.key}; use another axis letter",
                )
            axes_on[url + "|" + obj.axis] = obj
            for other in axes_on.values():
                if other.url == url and other.serial.baudrate != obj.serial.baudrate:
                    raise ctx.err(
                        f"{key}.baudrate",
                        f"{obj.serial.baudrate} differs from {other.key}.baudrate "
                        f"{other.serial.baudrate} on the same controller {url!r}",
                    )

    return RigConfig(
        name=name,
        turntable=turntable,
        geometry=geometry,
        light_array=light_array,
        backdrops=backdrops,
        cameras=tuple(cameras),
        panels=tuple(panels),
        raw=raw,
        source=source,
    )
