"""The simulated rig: real drivers, real emulators, Mitsuba cameras.

``open_sim_rig("sim:builtin:diffuse")`` reads a rig TOML (default
``opacityhull/sim/data/rig.toml``), starts an emulator for every ``emulator:KIND`` URL
(:func:`opacityhull.rigs.emulators.launch.start_emulators`, over ptys) and builds the
hardware rig's drivers on them (:func:`opacityhull.rigs.rig.open_rig`) — so the
turntable, light array and backdrops are the real GRBL / Enttec DMX / display-controller
drivers talking bytes to the emulators. Only the cameras are simulated: a
:class:`SimCamera` reads the *emulators'* state (table angle from the turntable axis,
light-array angle from its axis, DMX levels through the channel map, the pattern each
powered display shows) and renders it with Mitsuba. Calibration and reconstruction see
a rig they cannot tell from hardware except by image content.

Spec syntax: ``sim:SCENE[@RIG.toml][?key=value&...]`` — ``SCENE`` is ``builtin:NAME`` (or
just ``NAME`` for a built-in), or a scene TOML path; ``RIG.toml`` a rig TOML whose
serial devices are all ``emulator:`` URLs (a geometry-only TOML gets the default
emulated devices); options ``scale``, ``seed``, ``noise`` (0/1), ``time_scale``.

Camera values: ``gain * exposure_s * radiance`` (``gain`` from ``geometry.cameras[i]``),
optionally through :class:`~opacityhull.sim.sensor.SensorModel` (shot and read noise,
clipping at the white level 1.0, 12 bits) when ``sensor_noise=True``.
"""

from __future__ import annotations

import copy
import math
import threading
import tomllib
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, cast
from collections.abc import Iterator, Sequence
from urllib.parse import parse_qsl

import numpy as np

from ..charuco import CharucoSpec
from ..errors import ConfigError, DeviceError, InputError
from ..riggeometry import CameraSpec, RigGeometry
from ..rigs.cameras import check_exposure
from ..rigs.interfaces import CameraInfo, DeviceInfo
from .render import SimRenderer, SimState
from .scenes import DATA_DIR, SceneSpec, builtin_names, load_scene
from .sensor import SensorModel

if TYPE_CHECKING:
    from ..rigs.emulators.display import DisplayEmulator
    from ..rigs.emulators.enttec import EnttecEmulator
    from ..rigs.config import RigConfig
    from ..rigs.emulators.grbl import GrblEmulator
    from ..rigs.video import DisplayOutput

__all__ = [
    "SimRig",
    "SimCamera",
    "open_sim_rig",
    "bringup_sim_rig",
    "sim_rig_config",
    "parse_sim_spec",
    "DEFAULT_RIG_TOML",
    "OPERATOR_ACTIONS",
]

DEFAULT_RIG_TOML = DATA_DIR / "rig.toml"
OPERATOR_ACTIONS = ("place_board", "remove_board", "remove_object", "place_object")
_OPTION_KEYS = ("scale", "seed", "noise", "time_scale")


# --------------------------------------------------------------------------- spec and config


def parse_sim_spec(spec: str) -> tuple[str, str | None, dict]:
    """Split ``sim:SCENE[@RIG.toml][?opts]`` into (scene spec, rig TOML or None, options)."""
    if not isinstance(spec, str) or not spec.startswith("sim:"):
        raise ConfigError(f"simulated rig {spec!r}: expected sim:SCENE[@RIG.toml] (e.g. sim:builtin:diffuse)")
    body = spec[4:]
    opts: dict = {}
    if "?" in body:
        body, query = body.split("?", 1)
        for k, v in parse_qsl(query, keep_blank_values=True, strict_parsing=False):
            if k not in _OPTION_KEYS:
                raise ConfigError(f"simulated rig {spec!r}: unknown option {k!r} (allowed: {list(_OPTION_KEYS)})")
            try:
                opts[k] = float(v) if k in ("scale", "time_scale") else int(v)
            except ValueError:
                raise ConfigError(f"simulated rig {spec!r}: option {k}={v!r} is not a number") from None
    rig = None
    if "@" in body:
        body, rig = body.split("@", 1)
    if not body:
        raise ConfigError(f"simulated rig {spec!r}: no scene (built-ins: {builtin_names()})")
    if not body.startswith("builtin:") and not Path(body).exists() and body in builtin_names():
        body = f"builtin:{body}"
    return body, rig or None, opts


_DEFAULT_DEVICES_NOTE = "devices synthesised by the simulator for a geometry-only rig TOML"


def _default_devices(geometry: dict) -> dict:
    from ..rigs.config import emulated_axis

    lights = geometry.get("lights", [])
    displays = geometry.get("displays", [])
    dev: dict = {"turntable": emulated_axis("X", max_rate_deg_s=30.0, accel_deg_s2=60.0)}
    if lights:
        dev["light_array"] = {
            "url": "emulator:enttec",
            "timeout_s": 2.0,
            "rotation": emulated_axis("Y", max_rate_deg_s=30.0),
            "channels": {str(int(L.get("id", i))): i + 1 for i, L in enumerate(lights)},
        }
    if displays:
        dev["backdrops"] = {
            "url": "emulator:display",
            "timeout_s": 2.0,
            "outputs": {str(d.get("name", f"display{i}")): i for i, d in enumerate(displays)},
        }
    dev["cameras"] = [
        {"name": str(c.get("name", f"cam{i}")), "driver": "sim"} for i, c in enumerate(geometry.get("cameras", []))
    ]
    return dev


def _scale_geometry(geometry: dict, scale: float, where: str) -> dict:
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise ConfigError(f"{where}: scale must be a positive number, got {scale!r}")
    g = copy.deepcopy(geometry)
    if abs(scale - 1.0) < 1e-12:
        return g
    for c in g.get("cameras", []):
        w, h = c.get("width"), c.get("height")
        if not isinstance(w, (int, float)) or not isinstance(h, (int, float)):
            continue  # RigGeometry.from_dict reports the missing key
        nw, nh = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
        sx, sy = nw / w, nh / h
        c["width"], c["height"] = nw, nh
        if "focal_px" in c:
            c["focal_px"] = float(c["focal_px"]) * sy
        if "cx" in c:
            c["cx"] = (float(c["cx"]) + 0.5) * sx - 0.5
        if "cy" in c:
            c["cy"] = (float(c["cy"]) + 0.5) * sy - 0.5
    return g


def sim_rig_config(spec: str | None = None, *, rig_toml: str | Path | None = None, scale: float | None = None) -> dict:
    """The rig TOML content (``rig``, ``devices``, ``geometry``) of a simulated rig, without
    starting anything: the rig TOML (default :data:`DEFAULT_RIG_TOML`) with camera sizes
    multiplied by ``scale`` and ``emulator:`` devices filled in for geometry-only files.

    Raises
    ------
    ConfigError
        Unreadable TOML, no geometry, or a serial device that is not ``emulator:KIND``.
    """
    opts: dict = {}
    if spec is not None:
        _, rig_from_spec, opts = parse_sim_spec(spec)
        if rig_toml is None:
            rig_toml = rig_from_spec
    if scale is None:
        scale = float(opts["scale"]) if "scale" in opts else 1.0
    path = Path(rig_toml) if rig_toml is not None else DEFAULT_RIG_TOML
    if not path.is_file():
        raise ConfigError(f"rig TOML {path} not found")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: invalid TOML ({e})") from None
    if "geometry" not in raw:
        raise ConfigError(f"{path}: no [geometry] table (the simulated rig needs cameras, lights, displays)")
    raw = copy.deepcopy(raw)
    raw["geometry"] = _scale_geometry(raw["geometry"], float(scale), str(path))
    if "devices" not in raw:
        raw["devices"] = _default_devices(raw["geometry"])
        raw.setdefault("rig", {}).setdefault("description", _DEFAULT_DEVICES_NOTE)
    dev = raw["devices"]
    if "cameras" not in dev:
        dev["cameras"] = _default_devices(raw["geometry"])["cameras"]
    urls = []
    for k in ("turntable", "light_array", "backdrops"):
        if isinstance(dev.get(k), dict) and "url" in dev[k]:
            urls.append((f"devices.{k}.url", dev[k]["url"]))
    la = dev.get("light_array")
    if isinstance(la, dict) and isinstance(la.get("rotation"), dict) and "url" in la["rotation"]:
        urls.append(("devices.light_array.rotation.url", la["rotation"]["url"]))
    for key, url in urls:
        if not (isinstance(url, str) and url.startswith("emulator:")):
            raise ConfigError(
                f"{path}: {key} = {url!r}: a simulated rig drives emulators only "
                "(use emulator:grbl, emulator:enttec, emulator:display)"
            )
    for i, c in enumerate(dev.get("cameras", [])):
        if isinstance(c, dict) and c.get("driver", "sim") != "sim":
            raise ConfigError(
                f"{path}: devices.cameras[{i}].driver = {c.get('driver')!r}: a simulated rig renders "
                'its cameras (driver = "sim")'
            )
    raw.setdefault("rig", {}).setdefault("name", f"simulated rig ({path.name})")
    return raw


# --------------------------------------------------------------------------- camera


class SimCamera:
    """A camera of the simulated rig (implements ``CameraDevice``).

    ``capture(exposure_s)`` renders what the rig's emulators say is happening now and
    returns float32 (H, W, 3) sensor values ``gain * exposure_s * radiance`` (through the
    sensor model if the rig has one).
    """

    def __init__(self, index: int, spec: CameraSpec, rig: SimRig):
        self.index = int(index)
        self.name = spec.name
        self.spec = spec
        self._rig = rig
        self._captures = 0
        self._lock = threading.Lock()
        self.last_state: SimState | None = None
        self.last_effects = None
        self.last_passes: list = []
        self.last_seed: int | None = None

    @property
    def camera(self):
        """The true camera (pose in the rig frame)."""
        return self._rig.true_cameras[self.index]

    def capture(self, exposure_s: float) -> np.ndarray:
        exposure_s = check_exposure(self.name, exposure_s)
        rig = self._rig
        state = rig.state()
        with self._lock:
            n = self._captures
            self._captures += 1
        seed = (rig.seed * 1_000_003 + self.index * 10_007 + n) & 0x7FFFFFFF
        cfg = rig.renderer.effects_for(state, camera=self.camera)
        radiance = rig.renderer.render(self.camera, state, seed=seed)
        self.last_state, self.last_effects, self.last_seed = state, cfg, seed
        self.last_passes = rig.renderer.passes_for(state, camera=self.camera)
        value = (self.spec.gain * float(exposure_s)) * radiance
        if rig.sensor is not None:
            value = rig.sensor.apply(value, np.random.default_rng([rig.seed, self.index, n]))
        return value.astype(np.float32, copy=False)

    def info(self) -> CameraInfo:
        return CameraInfo(
            name=self.name,
            width=self.spec.width,
            height=self.spec.height,
            model=f"opacityhull sim camera (Mitsuba {self._rig.variant})",
            serial=f"sim-{self.index}",
            white_level=1.0,
            linear=True,
        )

    def check(self) -> DeviceInfo:
        return DeviceInfo(
            self.name,
            True,
            f"simulated {self.spec.width}x{self.spec.height}, Mitsuba {self._rig.variant}",
            identity="sim",
            state={"width": self.spec.width, "height": self.spec.height, "captures": self._captures},
        )

    def close(self) -> None:
        return None


# --------------------------------------------------------------------------- rig


class SimRig:
    """A simulated rig (implements ``Rig``): emulators + real drivers + Mitsuba cameras.

    Build it with :func:`open_sim_rig`. ``turntable``, ``light_array`` and ``backdrops``
    are the hardware drivers (from :func:`opacityhull.rigs.rig.open_rig`); ``emulators``
    the running :class:`~opacityhull.rigs.emulators.launch.EmulatorSet`; ``renderer`` the
    :class:`~opacityhull.sim.render.SimRenderer`.
    """

    def __init__(
        self,
        scene: SceneSpec,
        config_dict: dict,
        *,
        source: str,
        time_scale: float = 0.0,
        sensor_noise: bool = False,
        seed: int = 0,
        variant: str | None = None,
        overrides: dict | None = None,
        sensor: SensorModel | None = None,
    ):
        from ..rigs.config import parse_rig_config

        self.scene = scene
        self.source = source
        self.config_dict = config_dict
        self.config = parse_rig_config(config_dict, source=source)
        self.geometry: RigGeometry = self.config.geometry
        self.time_scale = float(time_scale)
        self.seed = int(seed)
        self.sensor = (sensor or SensorModel()) if sensor_noise else None
        self.renderer = SimRenderer(scene, self.geometry, variant=variant, overrides=overrides)
        self.true_cameras = self.geometry.nominal_cameras()
        self.cameras = [SimCamera(i, spec, self) for i, spec in enumerate(self.geometry.cameras)]
        self.emulators = None
        self._hw = None
        self.object_present = True
        self.board_present = False
        self.charuco: CharucoSpec | None = None
        self.operator_log: list[tuple[str, dict]] = []
        self.phase: str | None = None  # the capture phase declared by note_phase (None: undeclared)

    def fit_lamps(self, geometry: RigGeometry) -> None:
        """Render from now on with ``geometry``'s lamps (a plan's ``lamp_radius_m``:
        :func:`~opacityhull.acquire.schedule.lamps_for_plan`); cameras and displays must
        be this rig's. ``describe()`` and the session then record the lamps used."""
        self.config_dict = copy.deepcopy(self.config_dict)
        self.config_dict["geometry"] = copy.deepcopy(geometry.to_dict())
        from ..rigs.config import parse_rig_config

        self.config = parse_rig_config(self.config_dict, source=self.source)
        self.geometry = self.config.geometry
        r = self.renderer
        self.renderer = SimRenderer(self.scene, self.geometry, variant=r.variant, overrides=r.overrides)

    # ---- lifecycle
    @property
    def variant(self) -> str:
        return str(self.renderer.mi.variant())

    @property
    def is_open(self) -> bool:
        return self._hw is not None

    def open(self) -> SimRig:
        """Start the emulators and open the drivers on them (idempotent)."""
        if self._hw is not None:
            return self
        from ..rigs.emulators.launch import start_emulators
        from ..rigs.rig import open_rig

        emu = start_emulators(self.config, kind="pty", time_scale=self.time_scale)
        try:
            hw = open_rig(emu.config, cameras=self.cameras, interactive=False, assume_ready=True)
        except BaseException:
            emu.stop()
            raise
        self.emulators, self._hw = emu, hw
        return self

    def attach(self, hardware, emulators) -> SimRig:
        """Use ``hardware`` (a :class:`~opacityhull.rigs.rig.HardwareRig` built with this
        rig's :attr:`cameras`, its ports opened by the caller) over ``emulators`` started
        by the caller, instead of :meth:`open`: ``opacityhull rig bringup`` opens each port
        on its own and injects faults, where :meth:`open` would refuse a dead device.
        :meth:`detach` hands them back unclosed."""
        if self._hw is not None:
            raise DeviceError(f"simulated rig {self.source}: already open")
        self.emulators, self._hw = emulators, hardware
        return self

    def detach(self) -> None:
        """Forget the drivers and emulators given to :meth:`attach` (their owner closes them)."""
        self.emulators, self._hw = None, None

    def close(self) -> None:
        """Close the drivers and stop the emulators (the ptys disappear)."""
        hw, emu = self._hw, self.emulators
        self._hw = None
        try:
            if hw is not None:
                hw.close()
        finally:
            if emu is not None:
                emu.stop()
            self.emulators = None

    def __enter__(self) -> SimRig:
        return self.open()

    def __exit__(self, *exc):
        self.close()
        return False

    def _require(self):
        if self._hw is None:
            raise DeviceError(f"simulated rig {self.source}: not open (call open() or use it as a context manager)")
        return self._hw

    # ---- devices (the hardware drivers)
    @property
    def turntable(self):
        return self._require().turntable

    @property
    def light_array(self):
        return self._require().light_array

    @property
    def backdrops(self):
        return self._require().backdrops

    @property
    def hardware(self):
        """The underlying :class:`~opacityhull.rigs.rig.HardwareRig` (drivers)."""
        return self._require()

    @contextmanager
    def safe(self) -> Iterator[SimRig]:
        with self._require().safe():
            yield self

    def check(self) -> list[DeviceInfo]:
        return self._require().check()

    def describe(self) -> dict:
        """The rig TOML content with ``emulator:`` URLs (reproducible), plus a ``[sim]``
        table naming the scene, seed, sensor model and Mitsuba variant."""
        d = copy.deepcopy(self.config_dict)
        d["sim"] = {
            "scene": self.scene.source,
            "seed": self.seed,
            "sensor_noise": self.sensor is not None,
            "variant": self.variant,
            "time_scale": self.time_scale,
        }
        if self.sensor is not None:
            d["sim"]["sensor"] = self.sensor.to_dict()
        return d

    # ---- state
    def settle(self, timeout_s: float = 1.0) -> bool:
        """Wait (bounded) until the emulators have received what the drivers last sent.

        The DMX widget protocol has no acknowledgement: ``set_levels`` returns once the
        bytes are written to the port, before the emulator (like a real widget) has read
        them. A camera exposure starts after the lights have switched, so a capture
        first waits for the emulator's universe to equal the driver's last one. Returns
        False if it did not within ``timeout_s`` (a garbled or lost frame: the lights
        then show whatever the wire delivered).
        """
        import time

        hw, emu = self._hw, self.emulators
        if hw is None or emu is None or self.config.light_array is None:
            return True
        dmx = getattr(hw.light_array, "dmx", None)
        sent = getattr(dmx, "last_sent", None)
        if sent is None:
            return True
        dev = cast("EnttecEmulator", emu.by_device[self.config.light_array.name])
        deadline = time.monotonic() + timeout_s
        while True:
            got = dev.levels()
            if got[: len(sent)] == sent:
                return True
            if time.monotonic() > deadline:
                return False
            time.sleep(0.0005)

    def state(self, *, settle: bool = True) -> SimState:
        """What the emulators say the rig is doing now (and what stands on the table);
        first :meth:`settle` unless ``settle=False``."""
        if settle:
            self.settle()
        emu = self.emulators
        if emu is None:
            raise DeviceError(f"simulated rig {self.source}: not open — the emulators are not running")
        cfg = self.config
        by = emu.by_device
        table = cast("GrblEmulator", by[cfg.turntable.name]).position_deg(cfg.turntable.axis)
        array = 0.0
        levels: dict[int, int] = {}
        if cfg.light_array is not None:
            rot = cfg.light_array.rotation
            if rot is not None:
                array = cast("GrblEmulator", by[rot.name]).position_deg(rot.axis)
            universe = cast("EnttecEmulator", by[cfg.light_array.name]).levels()
            for lid, ch in cfg.light_array.channel_map.items():
                levels[int(lid)] = int(universe[ch - 1]) if ch - 1 < len(universe) else 0
        displays: dict[str, np.ndarray | None] = {}
        if cfg.backdrops is not None and cfg.backdrops.driver == "video":
            # monitors of a video output: the texture is what the DisplayOutput last drew
            out_dev = cast("DisplayOutput", self._require().backdrops)
            for name in cfg.backdrops.monitor_map:
                displays[name] = out_dev.current(name)
        elif cfg.backdrops is not None:
            dev = cast("DisplayEmulator", by[cfg.backdrops.name])
            for name, out in cfg.backdrops.output_map.items():
                pid = dev.shown(out) if dev.powered(out) else None
                displays[name] = dev.pattern(pid) if pid is not None else None
        if self.board_present:
            content = "board"
        elif self.object_present:
            content = "object"
        else:
            content = "none"
        return SimState(
            table_deg=float(table),
            array_deg=float(array),
            light_levels=levels,
            displays=displays,
            content=content,
            charuco=self.charuco,
            phase=self.phase,
        )

    def note_phase(self, phase: str | None) -> None:
        """Declare the capture phase of the shots that follow (None: undeclared).

        The rig state cannot tell a matting shot from an envmatte one (displays on,
        lights off), so undeclared shots are rendered with samples that keep both phases'
        error bounds; a declared ``matting`` shot gets the cheaper matting selection
        (:func:`~opacityhull.sim.effects.select_effects`, ``declared``). A capture runner
        calls this before the shots of each phase."""
        from .effects import PHASES

        if phase is not None and phase not in PHASES:
            raise InputError(f"note_phase: phase {phase!r}; expected one of {list(PHASES)} or None")
        self.phase = phase

    # ---- operator and ground truth
    def operator(self, action: str, **details) -> None:
        """Perform a manual step: ``place_board`` (``charuco=CharucoSpec``; default the
        scene's board or ``CharucoSpec()``), ``remove_board``, ``remove_object``,
        ``place_object``. The board, while present, replaces the object in renders and
        turns with the table."""
        if action not in OPERATOR_ACTIONS:
            raise InputError(f"operator action {action!r}: expected one of {list(OPERATOR_ACTIONS)}")
        self.operator_log.append((action, dict(details)))
        if action == "place_board":
            spec = details.get("charuco")
            if spec is None:
                boards = [p.charuco for p in self.scene.parts if p.kind == "board"]
                spec = boards[0] if boards else CharucoSpec()
            if not isinstance(spec, CharucoSpec):
                raise InputError(f"operator place_board: charuco must be a CharucoSpec, got {type(spec).__name__}")
            self.charuco = spec
            self.board_present = True
        elif action == "remove_board":
            self.board_present = False
        elif action == "remove_object":
            self.object_present = False
        elif action == "place_object":
            self.object_present = True

    def ground_truth(self, root, views: Sequence[tuple[int, float]], *, progress=None) -> Path:
        """Write ``root/groundtruth/`` for ``views`` (camera index, table angle): see
        :func:`opacityhull.sim.groundtruth.write_ground_truth`."""
        from .groundtruth import write_ground_truth

        return write_ground_truth(
            root,
            scene=self.scene,
            geometry=self.geometry,
            views=list(views),
            renderer=self.renderer,
            rig_cameras=self.true_cameras,
            progress=progress,
        )


def open_sim_rig(
    spec: str,
    *,
    rig_toml: str | Path | None = None,
    scale: float | None = None,
    time_scale: float = 0.0,
    sensor_noise: bool = False,
    seed: int = 0,
    variant: str | None = None,
    overrides: dict | None = None,
    open: bool = True,
) -> SimRig:
    """Build the simulated rig named by ``spec`` and (by default) open it.

    Parameters
    ----------
    spec : str
        ``sim:SCENE[@RIG.toml][?scale=..&seed=..&noise=0|1&time_scale=..]``.
    rig_toml : path, optional
        Rig TOML (overrides the one in ``spec``; default :data:`DEFAULT_RIG_TOML`).
    scale : float, optional
        Multiplies every camera's resolution (default: the spec's ``scale`` or 1).
    time_scale : float
        Emulator time per physical second of motion (0 = instant moves).
    sensor_noise : bool
        Pass captures through :class:`~opacityhull.sim.sensor.SensorModel`.
    seed : int
        Seeds render noise and sensor noise (per camera and capture count).
    variant : str, optional
        Mitsuba variant (default :func:`~opacityhull.sim.variants.choose_variant`).
    overrides : dict, optional
        Effect overrides for every capture (``select_effects(overrides=...)``).
    open : bool
        Start the emulators and open the drivers now (``SimRig.open()`` is idempotent).
    """
    scene_spec, rig_from_spec, opts = parse_sim_spec(spec)
    scene = load_scene(scene_spec)
    rig_path = rig_toml if rig_toml is not None else rig_from_spec
    cfg = sim_rig_config(None, rig_toml=rig_path, scale=scale if scale is not None else opts.get("scale", 1.0))
    rig = SimRig(
        scene,
        cfg,
        source=spec,
        time_scale=opts.get("time_scale", time_scale),
        sensor_noise=bool(opts.get("noise", sensor_noise)),
        seed=int(opts.get("seed", seed)),
        variant=variant,
        overrides=overrides,
    )
    if open:
        rig.open()
    return rig


def bringup_sim_rig(config: RigConfig, *, scene: str = "builtin:diffuse", spp: int = 4) -> SimRig:
    """The simulated rig of ``config`` (whose cameras are ``driver = "sim"``) rendering
    ``scene`` at ``spp`` samples per pixel, not opened: ``opacityhull rig bringup`` builds
    the drivers on its own emulators and attaches them (:meth:`SimRig.attach`)."""
    return SimRig(load_scene(scene), config.to_dict(), source=f"sim:{scene}@{config.source}", overrides={"spp": spp})
