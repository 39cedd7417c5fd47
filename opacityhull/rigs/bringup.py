"""``opacityhull rig bringup``: a guided, resumable walk through a rig, device by device.

Steps, in order (each prints what it checks, the measurement and a verdict):

1. ``answers:DEVICE`` — every port opens and every device answers its identity query
   (``rig check``); a device that does not is named with what to check, and the steps
   that need it are skipped, naming it.
2. ``panels`` — video-output panels with an MDC control port are locked (no energy
   saving, no backlight schedule, no dynamic contrast) and read back.
3. ``turntable`` — with the ChArUco board on the table, each camera photographs it at
   table angle 0 and 90° (then the table returns to 0); the board's pose, solved from its
   corners with the cameras' nominal intrinsics, must turn by 90 ± 1° in a camera that
   sees the board both times.
4. ``lamp:ID`` — each lamp alone (DMX level 255) must raise the camera's mean brightness
   over the all-dark image by at least ``lamp_rise`` (linear, white level 1).
5. ``display:NAME`` — the display shows white, then black; the camera pixels that change
   give the measured contrast (mean white / mean black), at least ``min_contrast``.
6. ``exposure:CAMERA`` — the plan's shortest exposure of a fully lit scene leaves at
   most ``max_clipped`` of the pixels at the white level (the bracket is unclipped).

Passed steps are recorded in a state file (JSON) and skipped when the walk is run
again, so a failed step is retried after the fix without redoing the others
(``restart`` starts over).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, field
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal, Protocol
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..charuco import CharucoSpec, detect_board, tonemap_for_detection
from ..errors import ConfigError, DeviceError, InputError
from .interfaces import DeviceInfo

log = logging.getLogger(__name__)

__all__ = [
    "StepResult",
    "BringupOptions",
    "run_bringup",
    "open_for_bringup",
    "board_rotation_deg",
    "SimulatedRig",
]

Verdict = Literal["pass", "fail", "skip"]


@dataclass
class StepResult:
    """One step: ``step`` id, the ``device`` it exercises, what it ``checks``, the
    ``measurement`` (numbers), the ``verdict`` and, unless it passed, ``what_to_check``."""

    step: str
    device: str
    checks: str
    verdict: Verdict
    measurement: dict[str, Any] = field(default_factory=dict)
    what_to_check: str = ""
    earlier: bool = False  # passed in an earlier run (resumed)

    def line(self) -> str:
        m = ", ".join(f"{k} = {_fmt(v)}" for k, v in self.measurement.items())
        text = f"[{self.verdict.upper():4s}] {self.step}: {self.checks}"
        if m:
            text += f" — {m}"
        if self.earlier:
            text += " (passed earlier)"
        if self.what_to_check:
            text += f"\n       {self.what_to_check}"
        return text


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return str(v)


@dataclass(frozen=True, kw_only=True)
class BringupOptions:
    """Thresholds and settings of the walk.

    Attributes
    ----------
    charuco : CharucoSpec
        The board placed on the table for the turntable step.
    exposure_s : float
        Exposure of the board, lamp and display photographs, seconds.
    bracket_s : sequence of float
        The exposure bracket checked for clipping (its shortest exposure counts).
    turn_deg, tolerance_deg : float
        The turntable turns by ``turn_deg`` and back; the board must follow within the tolerance.
    lamp_exposure_s : float or None
        Exposure of the lamp photographs (one lamp is dimmer than the array: the plan's
        reflectance exposure); None: ``exposure_s``.
    lamp_rise : float
        Least rise of the camera's mean brightness when one lamp lights (linear, 0..1).
    min_contrast : float
        Least white/black contrast of a display as the camera sees it.
    max_clipped : float
        Largest fraction of clipped pixels at the shortest exposure of the bracket.
    camera : int or None
        Camera used for the lamp, display and board steps (None: each step picks the
        camera that sees best).
    """

    charuco: CharucoSpec = CharucoSpec()
    exposure_s: float = 0.8
    bracket_s: tuple[float, ...] = (0.8,)
    turn_deg: float = 90.0
    tolerance_deg: float = 1.0
    lamp_exposure_s: float | None = None
    lamp_rise: float = 0.001
    min_contrast: float = 5.0
    max_clipped: float = 0.001
    camera: int | None = None


def board_rotation_deg(R_a: np.ndarray, R_b: np.ndarray, axis: np.ndarray | None = None) -> float:
    """Angle, degrees, of the rotation taking board pose ``R_a`` to ``R_b`` (3x3, both
    camera_from_board).

    Without ``axis``: the whole rotation's angle, ``arccos((trace(R_b R_aᵀ) − 1) / 2)``.
    With ``axis`` (unit 3-vector, camera frame: the table axis): the twist of that
    rotation about the axis (swing-twist decomposition of its quaternion), which ignores
    the tilt errors a pose from a few corners has about the other two axes.
    """
    R = np.asarray(R_b, dtype=np.float64) @ np.asarray(R_a, dtype=np.float64).T
    if axis is None:
        c = (float(np.trace(R)) - 1.0) / 2.0
        return math.degrees(math.acos(max(-1.0, min(1.0, c))))
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    n = np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    twist = 2.0 * math.atan2(float(np.dot([x, y, z], n)), float(w))
    deg = abs(math.degrees(twist)) % 360.0
    return 360.0 - deg if deg > 180.0 else deg


def _board_pose(image: np.ndarray, spec: CharucoSpec, K: np.ndarray) -> tuple[np.ndarray | None, int]:
    """camera_from_board rotation from the detected corners (None below 6 corners)."""
    import cv2

    a = np.asarray(image)
    gray = a if a.dtype == np.uint8 and a.ndim == 2 else tonemap_for_detection(a)
    obs = detect_board(gray, charuco=spec, upscale=(1, 2, 3))
    n = len(obs)
    if n < 6:
        return None, n
    ok, rvec, _ = cv2.solvePnP(
        obs.object_points.astype(np.float64), obs.image_points.astype(np.float64), K, np.zeros(5)
    )
    if not ok:
        return None, n
    R, _ = cv2.Rodrigues(rvec)
    return R, n


class _Walk:
    def __init__(self, rig, *, opts: BringupOptions, state: dict, restart: bool, emit: Callable[[StepResult], None]):
        self.rig = rig
        self.opts = opts
        self.state = state
        self.restart = restart
        self.emit = emit
        self.results: list[StepResult] = []
        self.dead: dict[str, str] = {}  # device -> why it cannot be used

    def done_before(self, step: str) -> bool:
        prev = self.state.get(step)
        return not self.restart and isinstance(prev, dict) and prev.get("verdict") == "pass"

    def record(self, r: StepResult) -> StepResult:
        self.results.append(r)
        if r.verdict == "pass" and not r.earlier:
            self.state[r.step] = asdict(r)
        elif r.verdict != "pass":
            self.state.pop(r.step, None)
        self.emit(r)
        return r

    def step(self, step: str, device: str, checks: str, needs: Sequence[str], fn: Callable[[], StepResult]) -> None:
        if self.done_before(step):
            prev = self.state[step]
            self.record(StepResult(step, device, checks, "pass", dict(prev.get("measurement", {})), earlier=True))
            return
        missing = [d for d in needs if d in self.dead]
        if missing:
            why = "; ".join(f"{d}: {self.dead[d]}" for d in missing)
            self.record(StepResult(step, device, checks, "skip", what_to_check=f"needs {', '.join(missing)} ({why})"))
            return
        try:
            r = fn()
        except (DeviceError, InputError, ConfigError, OSError) as e:
            r = StepResult(step, device, checks, "fail", what_to_check=f"{device}: {e}")
        self.record(r)

    def capture(self, cam: int, exposure_s: float | None = None) -> np.ndarray:
        return np.asarray(self.rig.cameras[cam].capture(self.opts.exposure_s if exposure_s is None else exposure_s))


def _display_setter(bd) -> Callable[[str, np.ndarray], object]:
    show_image = getattr(bd, "show_image", None)
    if callable(show_image):
        return lambda name, img: show_image(name, img)
    counter = iter(range(0xFF00, 0xFFFE))

    def via_store(name: str, img: np.ndarray) -> None:
        pid = next(counter)
        bd.upload(name, pid, img)
        bd.show(name, pid)

    return via_store


def run_bringup(
    rig,
    *,
    options: BringupOptions = BringupOptions(),
    state_path: str | Path | None = None,
    restart: bool = False,
    failed_ports: dict[str, str] | None = None,
    emit: Callable[[StepResult], None] = lambda r: None,
) -> list[StepResult]:
    """Walk ``rig`` (a :class:`~opacityhull.rigs.rig.HardwareRig` whose ports are open,
    or a simulated rig) through the bring-up steps; every step's result, in order.

    ``failed_ports`` names ports that did not open (device -> error); ``state_path``
    keeps the passed steps between runs. Leaves the rig safe (lights off, displays
    black, table at 0) whatever happened.
    """
    state: dict = {}
    path = Path(state_path) if state_path is not None else None
    if path is not None and path.is_file() and not restart:
        try:
            state = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ConfigError(f"{path}: unreadable bring-up state ({e}); pass --restart to start over") from None
        if not isinstance(state, dict):
            raise ConfigError(f"{path}: bring-up state is not a JSON object; pass --restart to start over")
    walk = _Walk(rig, opts=options, state=state, restart=restart, emit=emit)
    try:
        _walk(walk, failed_ports or {})
    finally:
        hw = getattr(rig, "hardware", rig)
        try:
            failures = hw.make_safe()
            for label, err in failures:
                log.warning("bring-up: making the rig safe: %s: %s", label, err)
        except Exception as e:  # noqa: BLE001  the walk's report matters more than the clean-up's
            log.warning("bring-up: making the rig safe failed: %s", e)
        if path is not None:
            from ..imageio import atomic_path

            with atomic_path(path) as tmp:
                tmp.write_text(json.dumps(state, indent=1))
    return walk.results


def _walk(w: _Walk, failed_ports: dict[str, str]) -> None:
    rig, o = w.rig, w.opts
    geometry = rig.geometry
    # ---- 1: every device answers
    infos: list[DeviceInfo] = rig.check()
    # the port each device talks through (two GRBL axes share one controller)
    port_of: dict[str, str] = {}
    devices: list[Any] = [rig.turntable, rig.light_array, rig.backdrops]
    if rig.light_array is not None:
        devices.append(rig.light_array.rotation)
    devices += list(getattr(rig.backdrops, "panels", {}).values())
    for dev in devices:
        if dev is not None:
            port = getattr(dev, "controller", None) or getattr(dev, "dmx", None) or dev
            port_of[dev.name] = port.name
    for info in infos:
        name = info.name
        # a port that did not open says why (the device's own check only finds it closed)
        err = failed_ports.get(port_of.get(name, name))
        ok, detail = (info.ok and err is None), (err or info.detail)
        if not ok:
            w.dead[name] = detail
        w.record(
            StepResult(
                f"answers:{name}",
                name,
                "the device answers its identity/state query",
                "pass" if ok else "fail",
                {"reply": detail} if ok else {},
                "" if ok else f"{name}: {detail}",
            )
        )
    for port, err in failed_ports.items():
        if port not in set(port_of.values()) | {i.name for i in infos}:
            w.dead[port] = err
            w.record(StepResult(f"answers:{port}", port, "the port opens", "fail", what_to_check=f"{port}: {err}"))
    tt = rig.turntable.name
    la = rig.light_array
    bd = rig.backdrops
    la_needs = [la.name] if la is not None else []
    bd_needs = [bd.name] if bd is not None else []
    # a dead device is left alone by the steps that only need it dark (lights off, black
    # displays): each of its commands would only wait for its timeout
    la_aux = la if la is not None and la.name not in w.dead else None
    bd_aux = bd if bd is not None and bd.name not in w.dead else None
    cams = list(range(len(rig.cameras)))

    # ---- 2: panels locked
    if bd is not None and callable(getattr(bd, "lock_panels", None)) and getattr(bd, "panels", None):

        def panels() -> StepResult:
            states = bd.lock_panels()
            drift = {d: list(s.drift) for d, s in states.items() if s.drift}
            meas = {d: f"{s.model} {s.brightness}/{s.contrast} {s.temperature_c} °C" for d, s in states.items()}
            if drift:
                return StepResult("panels", bd.name, "panels locked (no auto-brightness)", "fail", meas, f"{drift}")
            return StepResult(
                "panels", bd.name, "panels locked (no auto-brightness, no dynamic contrast)", "pass", meas
            )

        w.step("panels", bd.name, "panels locked", [p.name for p in bd.panels.values()], panels)

    # ---- 3: the turntable turns and the camera sees it
    checks = f"the board turns with the table by {o.turn_deg:g} ± {o.tolerance_deg:g}°"

    def turntable() -> StepResult:
        rig.operator("place_board", charuco=o.charuco)
        try:
            if la_aux is not None:
                la_aux.set_levels({lid: 255 for lid in la_aux.light_ids})
            if bd_aux is not None:
                bd_aux.blank()
            nominal = geometry.nominal_cameras()
            Ks = [c.K for c in nominal]
            # the table axis (rig +Y) in each camera's frame
            axes = [np.linalg.inv(c.world_from_cam)[:3, :3] @ np.array([0.0, 1.0, 0.0]) for c in nominal]
            pick = [o.camera] if o.camera is not None else cams
            rig.turntable.move_to(0.0)
            first = {c: _board_pose(w.capture(c), o.charuco, Ks[c]) for c in pick}
            rig.turntable.move_to(o.turn_deg)
            second = {c: _board_pose(w.capture(c), o.charuco, Ks[c]) for c in pick}
            rig.turntable.move_to(0.0)
            back = rig.turntable.position_deg()
        finally:
            if la_aux is not None:
                la_aux.all_off()
            rig.operator("remove_board")
        seen = [c for c in pick if first[c][0] is not None and second[c][0] is not None]
        if not seen:
            corners = {c: (first[c][1], second[c][1]) for c in pick}
            return StepResult(
                "turntable",
                tt,
                checks,
                "fail",
                {"corners (0°, turned)": corners},
                f"{tt}: no camera found the board at both angles — is the board on the table, lit and in view?",
            )
        per_cam = {}
        for c in seen:
            ra, rb = first[c][0], second[c][0]
            assert ra is not None and rb is not None
            per_cam[rig.cameras[c].name] = board_rotation_deg(ra, rb, axes[c])
        turned = float(np.median(list(per_cam.values())))
        meas = {"board turned (deg)": turned, "per camera": per_cam, "back at (deg)": back}
        ok = abs(turned - o.turn_deg) <= o.tolerance_deg and abs(back) <= o.tolerance_deg
        return StepResult(
            "turntable",
            tt,
            checks,
            "pass" if ok else "fail",
            meas,
            ""
            if ok
            else f"{tt}: the board turned {turned:.2f}° for {o.turn_deg:g}° — check steps_per_deg, belt slip "
            "and that the board lies still on the table",
        )

    w.step("turntable", tt, checks, [tt], turntable)

    # ---- 4: each lamp lights
    if la is not None:
        cam = o.camera if o.camera is not None else len(cams) - 1
        dark: dict[str, float] = {}

        def dark_mean() -> float:
            if "v" not in dark:
                la.all_off()
                if bd_aux is not None:
                    bd_aux.blank()
                dark["v"] = float(w.capture(cam, o.lamp_exposure_s).mean())
            return dark["v"]

        for lid in la.light_ids:
            lamp_checks = f"lamp {lid} alone raises the mean brightness by ≥ {o.lamp_rise:g}"

            def lamp(lid=lid, lamp_checks=lamp_checks) -> StepResult:
                d = dark_mean()
                la.set_levels({lid: 255})
                lit = float(w.capture(cam, o.lamp_exposure_s).mean())
                la.all_off()
                rise = lit - d
                ok = rise >= o.lamp_rise
                return StepResult(
                    f"lamp:{lid}",
                    la.name,
                    lamp_checks,
                    "pass" if ok else "fail",
                    {
                        "camera": rig.cameras[cam].name,
                        "exposure_s": o.lamp_exposure_s or o.exposure_s,
                        "dark": d,
                        "lit": lit,
                        "rise": rise,
                    },
                    ""
                    if ok
                    else f"{la.name}: lamp {lid} did not light — check its DMX channel, the dimmer pack's address "
                    "and fuse, the lamp, and the XLR chain",
                )

            w.step(f"lamp:{lid}", la.name, lamp_checks, la_needs, lamp)

    # ---- 5: each display shows white and black
    if bd is not None:
        show = _display_setter(bd)
        for spec in geometry.displays:
            name = spec.name
            disp_checks = f"display {name} white vs black: contrast ≥ {o.min_contrast:g}"

            def display(name=name, spec=spec, disp_checks=disp_checks) -> StepResult:
                if la_aux is not None:
                    la_aux.all_off()
                bd.blank()
                cols, rows = spec.resolution
                white = np.full((rows, cols, 3), 255, np.uint8)
                show(name, white)
                w_imgs = [w.capture(c) for c in cams]
                show(name, np.zeros_like(white))
                b_imgs = [w.capture(c) for c in cams]
                bd.blank()
                best = None
                for c in cams:
                    lw, lb = w_imgs[c].mean(axis=2), b_imgs[c].mean(axis=2)
                    diff = lw - lb
                    if diff.max() <= 0:
                        continue
                    region = diff > 0.5 * diff.max()
                    mw, mb = float(lw[region].mean()), float(lb[region].mean())
                    contrast = mw / max(mb, 1e-4)
                    if best is None or contrast > best[0]:
                        best = (contrast, c, mw, mb, int(region.sum()))
                if best is None:
                    return StepResult(
                        f"display:{name}",
                        bd.name,
                        disp_checks,
                        "fail",
                        {},
                        f"{bd.name}: no camera saw display {name} change — check its video cable, input source, "
                        "power, and (video output) the monitor it is mapped to",
                    )
                contrast, c, mw, mb, npx = best
                ok = contrast >= o.min_contrast
                return StepResult(
                    f"display:{name}",
                    bd.name,
                    disp_checks,
                    "pass" if ok else "fail",
                    {"camera": rig.cameras[c].name, "white": mw, "black": mb, "contrast": contrast, "pixels": npx},
                    ""
                    if ok
                    else f"{bd.name}: display {name} contrast {contrast:.1f} — check the panel's brightness and "
                    "contrast settings and stray light on it",
                )

            w.step(f"display:{name}", bd.name, disp_checks, bd_needs, display)

    # ---- 6: brackets unclipped
    t_min = min(o.bracket_s)
    for c in cams:
        cname = rig.cameras[c].name
        exp_checks = f"the shortest bracket exposure {t_min:g} s clips ≤ {o.max_clipped:.2%} of the pixels"

        def exposure(c=c, cname=cname, exp_checks=exp_checks) -> StepResult:
            if la_aux is not None:
                la_aux.set_levels({lid: 255 for lid in la_aux.light_ids})
            if bd_aux is not None:
                for spec in geometry.displays:
                    cols, rows = spec.resolution
                    _display_setter(bd_aux)(spec.name, np.full((rows, cols, 3), 255, np.uint8))
            try:
                img = w.capture(c, t_min)
            finally:
                if la_aux is not None:
                    la_aux.all_off()
                if bd_aux is not None:
                    bd_aux.blank()
            white = float(getattr(rig.cameras[c].info(), "white_level", 1.0))
            clipped = float((img.max(axis=2) >= 0.999 * white).mean())
            ok = clipped <= o.max_clipped
            return StepResult(
                f"exposure:{cname}",
                cname,
                exp_checks,
                "pass" if ok else "fail",
                {"exposure_s": t_min, "clipped": clipped, "max": float(img.max())},
                ""
                if ok
                else f"{cname}: {clipped:.2%} clipped at {t_min:g} s — add a shorter exposure to the bracket "
                "or close the aperture",
            )

        w.step(f"exposure:{cname}", cname, exp_checks, [], exposure)


class SimulatedRig(Protocol):
    """What :func:`open_for_bringup` needs of a simulated rig (``opacityhull.sim.simrig.SimRig``,
    injected by the caller: rigs/ knows nothing of the simulator): its ``cameras``, and
    ``attach`` / ``detach`` of the drivers and emulators opened here."""

    @property
    def cameras(self) -> Sequence[Any]: ...

    def attach(self, hardware: Any, emulators: Any) -> Any: ...

    def detach(self) -> None: ...


@contextmanager
def open_for_bringup(
    config,
    *,
    faults: dict[str, list[str]] | None = None,
    simulated: Callable[[Any], SimulatedRig] | None = None,
) -> Iterator[tuple[Any, dict[str, str]]]:
    """The rig of ``config`` with every port opened on its own (a port that does not open
    is reported, not raised): yields ``(rig, failed_ports)``.

    ``emulator:`` URLs are served here (with ``faults``, the specs of ``rig emulate
    --fault``). ``driver = "sim"`` cameras come from ``simulated(config)`` (the CLI gives
    ``opacityhull.sim.simrig.bringup_sim_rig``), a simulated rig that renders through the
    drivers opened here, reading the emulators' state.
    """
    from .config import RigConfig
    from .emulators.launch import start_emulators
    from .rig import build_rig

    cfg: RigConfig = config
    sim = bool(cfg.cameras) and all(c.driver == "sim" for c in cfg.cameras)
    if faults and not cfg.emulated():
        raise ConfigError(f"--fault: {cfg.source} has no emulator: devices to inject faults into")
    if sim and simulated is None:
        raise ConfigError(f'{cfg.source}: simulated cameras (driver = "sim") need the simulator (simulated=...)')
    emus = start_emulators(cfg, faults=faults) if cfg.emulated() else None
    try:
        runtime = emus.config if emus is not None else cfg
        sim_rig: SimulatedRig | None = None
        if sim:
            if emus is None:
                raise ConfigError(
                    f'{cfg.source}: simulated cameras (driver = "sim") need emulated devices (emulator:KIND URLs)'
                )
            assert simulated is not None
            sim_rig = simulated(cfg)
            hw = build_rig(runtime, cameras=list(sim_rig.cameras), interactive=False, assume_ready=True)
            # ports opened one by one below: SimRig.open() would refuse a dead device
            sim_rig.attach(hw, emus)
            rig: Any = sim_rig
        else:
            hw = build_rig(runtime)
            rig = hw
        failed: dict[str, str] = {}
        for port in hw.ports:
            try:
                port.open()
            except (DeviceError, OSError) as e:
                failed[port.name] = str(e)
        try:
            yield rig, failed
        finally:
            if sim_rig is not None:
                sim_rig.detach()
            hw.close()
    finally:
        if emus is not None:
            emus.stop()
