"""A hardware rig: the drivers of one rig TOML bundled as a :class:`~opacityhull.rigs.interfaces.Rig`.

:func:`open_rig` builds the drivers from a :class:`~opacityhull.rigs.config.RigConfig`
(one GRBL controller per distinct URL, shared by the axes on it) and opens them;
:class:`HardwareRig` adds what a capture needs around them: ``safe()`` (lights off,
backdrops blank, feed hold on every exit, Ctrl-C included), bounded reconnects,
``check()``, ``describe()`` and the operator prompts between capture phases.

:func:`check_rig_config` talks to every device of a config separately, with short
timeouts and no reconnects, and never raises for a device failure — it is what
``opacityhull rig check`` runs.
"""

from __future__ import annotations

import logging
import signal
import sys
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any
from collections.abc import Callable, Iterator, Sequence

from ..errors import CaptureInterrupted, ConfigError, DeviceError, Terminated
from ..interrupts import deferred_signals
from .config import AxisConfig, CameraConfig, RigConfig, load_rig_config, parse_emulator_url
from .backdrops import DisplayController
from .interfaces import Backdrops, CameraDevice, DeviceInfo, LightArray, Port, RotaryAxis, Turntable
from .lights import DmxLightArray, EnttecDmx
from .motion import GrblAxis, GrblController, GrblInterrupted
from .panels import MdcPanel
from .video import DisplayOutput
from .transport import DeviceGone, OpenClose, SerialSettings, reopen

if TYPE_CHECKING:  # cameras.py imports the image codecs: only when a camera is built
    from .cameras import DirectoryCamera, OpenCVCamera

log = logging.getLogger(__name__)

__all__ = [
    "HardwareRig",
    "open_rig",
    "build_rig",
    "check_rig_config",
    "OperatorActionRequired",
    "OPERATOR_PROMPTS",
    "SIM_CAMERA_DETAIL",
]

SIM_CAMERA_DETAIL = "simulated: checked by sim"

#: What the operator is asked to do for each action of :meth:`HardwareRig.operator`.
OPERATOR_PROMPTS = {
    "place_board": "Place the ChArUco calibration board flat on the turntable, centred on the axis{board}.",
    "remove_board": "Remove the calibration board from the turntable.",
    "remove_object": "Remove the object from the turntable (background-only captures follow); touch nothing else.",
    "place_object": "Place the object on the turntable, centred on the axis, inside the capture volume.",
}


class OperatorActionRequired(CaptureInterrupted):
    """A manual step is needed and nobody is at the terminal to do it (non-interactive run)."""


def _board_text(details: dict) -> str:
    spec = details.get("charuco")
    if spec is None:
        return ""
    try:
        return (
            f" ({spec.squares_x}x{spec.squares_y} squares of {spec.square_m * 1000:g} mm, {spec.dictionary}"
            f", offset {tuple(spec.offset_m)} m, yaw {spec.yaw_deg:g}°)"
        )
    except AttributeError:
        return f" ({spec})"


class HardwareRig(OpenClose):
    """Devices plus geometry, implementing :class:`~opacityhull.rigs.interfaces.Rig`.

    Parameters
    ----------
    config : RigConfig
    turntable : Turntable
    light_array : LightArray, optional
    backdrops : Backdrops, optional
    cameras : sequence of CameraDevice, in ``geometry.cameras`` order
    ports : sequence of Port
        The connections to open, close and reconnect (GRBL controllers, DMX widget,
        display controller), each once, in opening order (:func:`build_rig` lists them).
    interactive : bool, optional
        Whether :meth:`operator` may prompt on the terminal; default: stdin is a tty.
    assume_ready : bool
        Non-interactive runs treat every operator action as done (scripts, emulated rigs).
    reconnect_attempts, reconnect_delay_s :
        Bound on :meth:`open` / :meth:`reconnect` retries of a port that is not there.
    input_fn : callable, optional
        Reads the operator's Enter (default :func:`input`).
    clear_hold : bool
        When a GRBL controller is found in a feed hold on :meth:`open` (left by an earlier
        ``safe()`` exit), clear it with a soft reset (GRBL keeps its position after the
        hold has decelerated to ``Hold:0``).
    """

    def __init__(
        self,
        config: RigConfig,
        *,
        turntable: Turntable,
        light_array: LightArray | None = None,
        backdrops: Backdrops | None = None,
        cameras: Sequence[CameraDevice] = (),
        ports: Sequence[Port] = (),
        interactive: bool | None = None,
        assume_ready: bool = False,
        reconnect_attempts: int = 3,
        reconnect_delay_s: float = 0.5,
        input_fn: Callable[[str], str] | None = None,
        clear_hold: bool = True,
    ):
        self.config = config
        self.geometry = config.geometry
        self.turntable = turntable
        self.light_array = light_array
        self.backdrops = backdrops
        self.cameras = list(cameras)
        self.interactive = interactive
        self.assume_ready = assume_ready
        self.reconnect_attempts = int(reconnect_attempts)
        self.reconnect_delay_s = float(reconnect_delay_s)
        self._input = input_fn
        self.clear_hold = bool(clear_hold)
        self._ports: list[Port] = []
        for p in ports:
            if not isinstance(p, Port):
                raise ConfigError(
                    f"rig {config.name}: ports: {type(p).__name__} is not a Port (name, url, is_open, open(), close())"
                )
            if all(p is not q for q in self._ports):
                self._ports.append(p)
        self._open = False
        self.safe_errors: list[tuple[str, str]] = []  # (step, error) of the last safe() exit
        self.operator_log: list[tuple[str, dict]] = []

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def ports(self) -> list[Port]:
        return list(self._ports)

    # ---- lifecycle
    def _open_port(self, port: Port, attempts: int) -> None:
        def once(_attempt: int) -> None:
            try:
                port.open()
            except GrblInterrupted as e:
                # A feed hold left by an earlier safe() exit: GRBL keeps its position through
                # a soft reset from Hold:0, and the reset clears the hold.
                if not (self.clear_hold and e.state == "Hold" and isinstance(port, GrblController)):
                    raise
                # A reset during Hold:1 (still decelerating) would lose the position: give
                # the slowest axis on this controller time to stop first.
                log.info("%s: clearing a feed hold left by an earlier run (soft reset)", port.name)
                time.sleep(port.stop_time_s() + 0.1)
                port.open(reset=True)

        def gave_up(tries: int, last: BaseException | None) -> DeviceGone:
            return DeviceGone(f"{port.name}: could not open {port.url} after {tries} attempt(s) ({last})")

        reopen(once, attempts=attempts, delay_s=self.reconnect_delay_s, gave_up=gave_up)

    def open(self) -> HardwareRig:
        """Open every port (each retried up to ``reconnect_attempts`` times); on failure the ports
        already opened are closed again and the error names the device."""
        if self._open:
            return self
        opened = []
        try:
            for p in self._ports:
                self._open_port(p, self.reconnect_attempts)
                opened.append(p)
        except BaseException:
            for p in reversed(opened):
                try:
                    p.close()
                except Exception as e:  # noqa: BLE001  the error that stopped open() is the one to report
                    log.warning("%s: close after a failed open failed: %s", p.name, e)
            raise
        self._open = True
        return self

    def close(self) -> None:
        """Close every port and camera (each attempted even if another fails)."""
        for p in reversed(self._ports):
            try:
                p.close()
            except Exception as e:  # noqa: BLE001  a dead port must not keep the others open
                log.warning("%s: close failed: %s", p.name, e)
        for c in self.cameras:
            close = getattr(c, "close", None)  # optional: CameraDevice has no close()
            if close is not None:
                try:
                    close()
                except Exception as e:  # noqa: BLE001  a dead camera must not keep the others open
                    log.warning("%s: close failed: %s", c.name, e)
        self._open = False

    def reconnect(
        self, device: str | None = None, *, max_attempts: int | None = None, delay_s: float | None = None
    ) -> None:
        """Close and re-open one port (by device name) or all, up to ``max_attempts`` tries
        each; raise :class:`DeviceGone` naming the device if it does not come back."""
        n = self.reconnect_attempts if max_attempts is None else int(max_attempts)
        old_delay = self.reconnect_delay_s
        if delay_s is not None:
            self.reconnect_delay_s = float(delay_s)
        try:
            ports = self._ports if device is None else [p for p in self._ports if p.name == device]
            if not ports:
                names = [p.name for p in self._ports]
                raise ConfigError(f"rig {self.name}: no port named {device!r} (ports: {names})")
            for p in ports:
                try:
                    p.close()
                except Exception as e:  # noqa: BLE001  it is being re-opened: the open below reports what matters
                    log.debug("%s: close before reconnect failed: %s", p.name, e)
                self._open_port(p, n)
        finally:
            self.reconnect_delay_s = old_delay

    # ---- safety
    def _axes(self) -> list[RotaryAxis]:
        axes: list[RotaryAxis] = [self.turntable]
        rot = self.light_array.rotation if self.light_array is not None else None
        if rot is not None and rot is not self.turntable:
            axes.append(rot)
        return axes

    def make_safe(self) -> list[tuple[str, str]]:
        """Feed hold on every axis, every light off, every backdrop blank. Each step is
        attempted even if another fails; returns the failures as ``(step, error)``."""
        failures: list[tuple[str, str]] = []

        def step(label: str, fn: Callable[[], object]) -> None:
            try:
                fn()
            except BaseException as e:  # noqa: BLE001 - a Ctrl-C inside one step must not skip the others
                failures.append((label, f"{type(e).__name__}: {e}"))

        for ax in self._axes():
            step(f"{ax.name}: feed hold", ax.stop)
        if self.light_array is not None:
            step(f"{self.light_array.name}: all off", self.light_array.all_off)
            err = self.light_array.last_error
            if err:
                failures.append((f"{self.light_array.name}: all off", str(err)))
        if self.backdrops is not None:
            step(f"{self.backdrops.name}: blank", self.backdrops.blank)
            err = self.backdrops.last_error
            if err:
                failures.append((f"{self.backdrops.name}: blank", str(err)))
        for label, error in failures:
            log.warning("rig %s: make safe: %s: %s", self.name, label, error)
        return failures

    @contextmanager
    def safe(self) -> Iterator[HardwareRig]:
        """``with rig.safe():`` — on any exit (normal, exception, Ctrl-C) the axes get a feed
        hold, the lights go off and the backdrops go blank.

        A second Ctrl-C during the clean-up is held back until the clean-up is done. If
        the body succeeded but the clean-up failed, :class:`DeviceError` names the steps
        that failed; if the body raised, that exception propagates and the clean-up
        failures are issued as a warning (and kept in :attr:`safe_errors`).
        """
        ok = False
        try:
            yield self
            ok = True
        finally:
            # SIGTERM/SIGHUP too: a capture turns them into an interrupt (acquire.runner),
            # and one arriving mid-clean-up must not cut the lights-off short either
            with deferred_signals("rig clean-up", deliver=False) as pending:
                self.safe_errors = self.make_safe()
            if self.safe_errors:
                text = "; ".join(f"{s}: {e}" for s, e in self.safe_errors)
                if ok and not pending:
                    raise DeviceError(
                        f"rig {self.name}: could not make the rig safe ({text}) — "
                        "switch the lights and displays off and stop the motors by hand"
                    )
                warnings.warn(f"rig {self.name}: clean-up incomplete: {text}", RuntimeWarning, stacklevel=3)
            if pending and ok:
                if pending[0] == signal.SIGINT:
                    raise KeyboardInterrupt
                raise Terminated(pending[0])

    # ---- queries
    def check(self) -> list[DeviceInfo]:
        """One :class:`DeviceInfo` per device (axes, lights, backdrops, cameras); never raises."""
        out = []
        devices: list[RotaryAxis | LightArray | Backdrops] = list(self._axes())
        devices += [d for d in (self.light_array, self.backdrops) if d is not None]
        for dev in devices:
            out.append(_safe_check(dev))
        for panel in getattr(self.backdrops, "panels", {}).values():
            out.append(_safe_check(panel))
        for i, cam in enumerate(self.cameras):
            cfg = self.config.cameras[i] if i < len(self.config.cameras) else None
            out.append(_camera_check(cam, cfg))
        return out

    def describe(self) -> dict[str, Any]:
        """The rig TOML content (``rig``, ``devices``, ``geometry``) to record in a session."""
        return self.config.to_dict()

    def operator(self, action: str, **details: Any) -> None:
        """Ask the operator to do ``action`` and wait for Enter.

        Non-interactive (stdin is not a terminal, or ``interactive=False``): with
        ``assume_ready`` the action is logged and taken as done; otherwise
        :class:`OperatorActionRequired` (exit code 5: the capture can be resumed) says
        what to do.
        """
        template = OPERATOR_PROMPTS.get(action)
        text = (
            template.format(board=_board_text(details))
            if template
            else f"Operator action {action!r}" + (f": {details}" if details else "") + "."
        )
        self.operator_log.append((action, dict(details)))
        interactive = self.interactive if self.interactive is not None else _stdin_is_tty()
        if not interactive:
            if self.assume_ready:
                sys.stderr.write(f"[{self.name}] operator: {text} (assumed done: non-interactive run)\n")
                sys.stderr.flush()
                return
            raise OperatorActionRequired(
                f"rig {self.name}: a manual step is needed — {text} Run the capture in a terminal to be prompted, "
                "or pass assume_ready (e.g. --assume-ready) if the step is already done; the capture can be resumed."
            )
        read = self._input or input
        sys.stderr.write(f"\n[{self.name}] {text}\n")
        sys.stderr.flush()
        try:
            read("Press Enter when done (Ctrl-C to stop)... ")
        except EOFError:
            raise OperatorActionRequired(f"rig {self.name}: stdin closed while waiting for: {text}") from None


def _stdin_is_tty() -> bool:
    try:
        return sys.stdin is not None and sys.stdin.isatty()
    except (ValueError, AttributeError):
        return False


def _safe_check(dev) -> DeviceInfo:
    name = getattr(dev, "name", type(dev).__name__)
    try:
        info = dev.check()
    except Exception as e:  # noqa: BLE001  check() should not raise, but a driver bug must not hide the others
        return DeviceInfo(name, False, f"{type(e).__name__}: {e}")
    return info


def _camera_check(cam, cfg: CameraConfig | None) -> DeviceInfo:
    name = getattr(cam, "name", cfg.name if cfg else "camera")
    if hasattr(cam, "check"):
        return _safe_check(cam)
    try:
        info = cam.info()
    except Exception as e:  # noqa: BLE001  reported as a failed check, like _safe_check
        return DeviceInfo(name, False, f"{type(e).__name__}: {e}")
    return DeviceInfo(
        name,
        True,
        f"{info.model or type(cam).__name__} {info.width}x{info.height}",
        identity=info.model,
        state={"width": info.width, "height": info.height},
    )


# --------------------------------------------------------------------------- building drivers


def _check_runnable_url(url: str, key: str, source: str) -> None:
    if parse_emulator_url(url) is not None:
        raise ConfigError(
            f"{source}: {key}.url is {url!r}: emulator URLs must be started first — run "
            "`opacityhull rig emulate --config RIG.toml --write-config RUNTIME.toml` and use RUNTIME.toml, or "
            "start_emulators(config) in Python"
        )


@dataclass(frozen=True, kw_only=True)
class _Devices:
    """The serial drivers of a config (no I/O yet) and the port each device talks through."""

    turntable: GrblAxis
    light_array: DmxLightArray | None
    backdrops: DisplayController | DisplayOutput | None
    ports: list[Port]
    #: (device, the port it talks through), in check order
    checks: list[tuple[GrblAxis | DmxLightArray | DisplayController | DisplayOutput | MdcPanel, Port]]


def _build_devices(config: RigConfig, *, timeout_s: float | None = None) -> _Devices:
    """Driver objects (no I/O) for the serial devices of ``config``."""
    controllers: dict[str, GrblController] = {}
    ports: list[Port] = []
    checks: list[tuple[GrblAxis | DmxLightArray | DisplayController | DisplayOutput | MdcPanel, Port]] = []

    def serial(s: SerialSettings, **quick: int) -> SerialSettings:
        """The device's settings; with ``timeout_s`` (a check), that timeout and ``quick``."""
        return s if timeout_s is None else replace(s, timeout_s=timeout_s, **quick)

    def controller(ax: AxisConfig) -> GrblController:
        if ax.url not in controllers:
            _check_runnable_url(ax.url, ax.key, config.source)
            names = [a.name for a in config.grbl_ports()[ax.url]]
            c = GrblController.from_url(
                ax.url, name="+".join(names) if len(names) > 1 else ax.name, serial=serial(ax.serial)
            )
            controllers[ax.url] = c
            ports.append(c)
        return controllers[ax.url]

    def axis(ax: AxisConfig) -> GrblAxis:
        a = GrblAxis(
            controller(ax),
            axis=ax.axis,
            steps_per_deg=ax.steps_per_deg,
            max_rate_deg_s=ax.max_rate_deg_s,
            accel_deg_s2=ax.accel_deg_s2,
            backlash_deg=ax.backlash_deg,
            soft_limits_deg=ax.soft_limits_deg,
            name=ax.name,
        )
        checks.append((a, a.controller))
        return a

    turntable = axis(config.turntable)
    light_array = None
    if config.light_array is not None:
        la = config.light_array
        _check_runnable_url(la.url, la.key, config.source)
        dmx = EnttecDmx.from_url(la.url, name=f"{la.name}.dmx", serial=serial(la.serial))
        ports.append(dmx)
        rotation = axis(la.rotation) if la.rotation is not None else None
        light_array = DmxLightArray(dmx, channels=la.channel_map, rotation=rotation, name=la.name)
        checks.append((light_array, dmx))
    backdrops: DisplayController | DisplayOutput | None = None
    panels: dict[str, MdcPanel] = {}
    for pc in config.panels:
        _check_runnable_url(pc.url, pc.key, config.source)
        panels[pc.display] = MdcPanel.from_url(
            pc.url,
            display_id=pc.display_id,
            name=pc.name,
            serial=serial(pc.serial, retries=0, reconnect_attempts=0),
            settings=pc.settings,
        )
    if config.backdrops is not None and config.backdrops.driver == "video":
        bd = config.backdrops
        backdrops = DisplayOutput(
            monitors=bd.monitor_map,
            response_s=bd.response_ms / 1000.0,
            name=bd.name,
            x_display=bd.x_display,
            panels=panels,
        )
        if timeout_s is None:  # a check resolves the monitors and opens no window
            ports.append(backdrops)
        checks.append((backdrops, backdrops))
        for p in panels.values():
            ports.append(p)
            checks.append((p, p))
    elif config.backdrops is not None:
        bd = config.backdrops
        _check_runnable_url(bd.url, bd.key, config.source)
        backdrops = DisplayController.from_url(
            bd.url,
            outputs=bd.output_map,
            name=bd.name,
            serial=serial(bd.serial, retries=0, reconnect_attempts=0),
            chunk_bytes=bd.chunk_bytes,
        )
        ports.append(backdrops)
        checks.append((backdrops, backdrops))
    return _Devices(turntable=turntable, light_array=light_array, backdrops=backdrops, ports=ports, checks=checks)


def _build_camera(c: CameraConfig, source: str) -> OpenCVCamera | DirectoryCamera:
    from .cameras import DirectoryCamera, OpenCVCamera

    opts = dict(c.options)
    if c.driver == "opencv":
        return OpenCVCamera(c.device, name=c.name, width=c.width, height=c.height, **opts)
    if c.driver == "directory":
        return DirectoryCamera(c.device, name=c.name, width=c.width, height=c.height, **opts)
    raise ConfigError(
        f'{source}: {c.key}.driver = "sim": simulated cameras render through the simulator — use '
        '`--rig sim:SCENE` (or pass cameras= to open_rig), or give this camera driver = "opencv" or "directory"'
    )


def build_rig(config_or_path, *, cameras: Sequence[CameraDevice] | None = None, **rig_kwargs) -> HardwareRig:
    """Build the drivers of a rig without opening anything (see :func:`open_rig`)."""
    config = config_or_path if isinstance(config_or_path, RigConfig) else load_rig_config(config_or_path)
    geo_names = [c.name for c in config.geometry.cameras]
    if cameras is not None:
        cams = list(cameras)
        names = [getattr(c, "name", None) for c in cams]
        if names != geo_names:
            raise ConfigError(
                f"{config.source}: injected cameras {names} must match geometry.cameras {geo_names} in name and order"
            )
    else:
        if not config.cameras:
            raise ConfigError(
                f"{config.source}: devices.cameras: no [[devices.cameras]] entries — add one per "
                f"geometry camera {geo_names}, or pass cameras= to open_rig"
            )
        cams = [_build_camera(c, config.source) for c in config.cameras]
    d = _build_devices(config)
    return HardwareRig(
        config,
        turntable=d.turntable,
        light_array=d.light_array,
        backdrops=d.backdrops,
        cameras=cams,
        ports=d.ports,
        **rig_kwargs,
    )


def open_rig(config_or_path, *, cameras: Sequence[CameraDevice] | None = None, **rig_kwargs) -> HardwareRig:
    """Build the rig of a config (or rig TOML path) and open its ports.

    Parameters
    ----------
    config_or_path : RigConfig or path
        ``emulator:`` URLs must have been replaced by real ones (:func:`start_emulators`
        returns such a config; ``opacityhull rig emulate`` writes one).
    cameras : sequence of CameraDevice, optional
        Camera drivers to use instead of ``[[devices.cameras]]`` (the simulator injects
        its own), in ``geometry.cameras`` order. Without them, ``driver = "sim"`` cameras
        raise :class:`ConfigError`.
    **rig_kwargs
        Passed to :class:`HardwareRig` (``interactive``, ``assume_ready``,
        ``reconnect_attempts``, ``reconnect_delay_s``, ``input_fn``).

    Use as ``with open_rig(path) as rig, rig.safe(): ...`` so the ports close on exit.
    """
    rig = build_rig(config_or_path, cameras=cameras, **rig_kwargs)
    rig.open()
    return rig


def check_rig_config(config_or_path, *, timeout_s: float = 1.0) -> list[DeviceInfo]:
    """Talk to every device of a rig config and report identity and state, one
    :class:`DeviceInfo` per device; never raises for a device that fails.

    Each device is opened on its own with ``timeout_s`` per reply and no retries or
    reconnects, so a dead device costs about one timeout. Cameras with ``driver = "sim"``
    are reported ok with :data:`SIM_CAMERA_DETAIL`. A config that still has
    ``emulator:`` URLs raises :class:`ConfigError` (start the emulators first).
    """
    config = config_or_path if isinstance(config_or_path, RigConfig) else load_rig_config(config_or_path)
    out: list[DeviceInfo] = []
    emulated = [k for k, u in config.device_urls().items() if parse_emulator_url(u) is not None]
    if emulated:
        raise ConfigError(
            f"{config.source}: {', '.join(emulated)} have emulator:KIND URLs, which only `opacityhull rig emulate "
            f"--config {config.source} --write-config RUNTIME.toml` can serve; check RUNTIME.toml instead"
        )
    d = _build_devices(config, timeout_s=timeout_s)
    from .motion import GrblInterrupted

    port_failed: dict[int, DeviceInfo | None] = {}
    for p in d.ports:
        try:
            p.open()
            port_failed[id(p)] = None
        except GrblInterrupted as e:
            if e.state == "Hold" and e.substate == 0:
                # what rig.safe() leaves after a capture stops: not "busy — another program"
                port_failed[id(p)] = DeviceInfo(
                    p.name, True, f"Hold:0 on {p.url}: stopped by a feed hold, as a capture's safe stop leaves it"
                )
            else:
                port_failed[id(p)] = DeviceInfo(p.name, False, str(e))
        except (DeviceError, OSError) as e:
            port_failed[id(p)] = DeviceInfo(p.name, False, str(e))
    try:
        for dev, port in d.checks:
            failed = port_failed.get(id(port))
            if failed is not None and failed.ok:
                out.append(DeviceInfo(dev.name, True, failed.detail, state={"state": "Hold", "substate": 0}))
            elif failed is not None:
                out.append(DeviceInfo(dev.name, False, failed.detail))
            else:
                out.append(_safe_check(dev))
    finally:
        for p in d.ports:
            try:
                p.close()
            except Exception as e:  # noqa: BLE001  the report is what matters here; a close failure must not hide it
                log.debug("%s: close failed: %s", p.name, e)
    for c in config.cameras:
        if c.driver == "sim":
            out.append(DeviceInfo(c.name, True, SIM_CAMERA_DETAIL, identity="sim"))
            continue
        try:
            cam = _build_camera(c, config.source)
        except (ConfigError, DeviceError) as e:
            out.append(DeviceInfo(c.name, False, str(e)))
            continue
        cam.timeout_s = min(cam.timeout_s, max(timeout_s, 2.0))
        out.append(_camera_check(cam, c))
        close = getattr(cam, "close", None)
        if close is not None:
            close()
    return out
