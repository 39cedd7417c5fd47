"""A small laboratory rig for the capture tests: the real drivers over ptys to the
real emulators, and a camera that synthesises its image from the emulators' state
(no Mitsuba, so a capture of a few hundred images takes seconds).

* :func:`opacityhull.rigs.emulators.launch.start_emulators` runs a GRBL controller
  (turntable axis X, light-array rotation axis Y), an Enttec DMX USB Pro and the
  display controller, each behind a pty; :func:`opacityhull.rigs.rig.build_rig` builds
  the real drivers (:class:`~opacityhull.rigs.rig.HardwareRig`, with its ``safe()``).
* :class:`SynthCamera` renders from the emulator state: the bottom display as the
  display emulator shows it, behind a disk "object" lit by the DMX levels the Enttec
  emulator outputs; ``value = gain * t * L`` clipped at the white level.
* :class:`LabRig` is the HardwareRig plus a scene (object / board on the table) that
  the operator steps change, and a ground-truth writer (like a simulated rig).

Usable in a subprocess (the SIGINT/SIGKILL tests): ``python rigkit.py OUT [--resume]``
captures :data:`TINY_PLAN` and prints ``img <n>`` after every image.
"""

from __future__ import annotations

import json
import math
import sys
import threading
from pathlib import Path

import numpy as np

from opacityhull.errors import DeviceError
from opacityhull.rigs.protocols import CameraInfo

GEOMETRY = {
    "target_m": [0.0, 0.08, 0.0],
    "cameras": [
        {"name": f"cam{i}", "width": 24, "height": 18, "distance_m": 1.0, "elevation_deg": 10.0 + 15 * i,
         "azimuth_deg": 0.0, "fov_y_deg": 30.0, "gain": 1.0}
        for i in range(3)
    ],
    "lights": [{"id": i, "elevation_deg": 45.0, "azimuth_deg": 90.0 * i, "distance_m": 1.2} for i in range(4)],
    "displays": [
        {"name": "bottom", "centre_m": [0.0, 0.0, 0.0], "normal": [0.0, 1.0, 0.0], "up": [0.0, 0.0, -1.0],
         "size_m": [0.6, 0.6], "resolution": [16, 16], "rotates_with_table": True},
        {"name": "back", "centre_m": [0.0, 0.3, -0.4], "normal": [0.0, 0.0, 1.0], "up": [0.0, 1.0, 0.0],
         "size_m": [0.8, 0.6], "resolution": [16, 12], "rotates_with_table": False},
    ],
}

TINY_PLAN = {
    "plan": {"name": "lab-tiny", "seed": 5},
    "table": {"steps": 4},
    "exposures": {"default_s": [0.5]},
    "phases": {
        "calibration": {"count": 2, "charuco": {"squares_x": 5, "squares_y": 4, "square_m": 0.04, "marker_m": 0.03}},
        "matting": {"patterns": 2, "object_absent": True, "cell_px": 2},
        "lightfield": {"level": 200},
        "reflectance": {"array_steps": 2, "lights": 2, "exposures_s": [0.25, 1.0]},
    },
}


class SynthCamera:
    """Image from the rig state: backdrop (bottom display as the emulator shows it) and
    a lit disk when the object is on the table; a checkerboard when the board is."""

    def __init__(self, rig: "LabRig", index: int):
        self.rig = rig
        self.index = index
        spec = rig.geometry.cameras[index]
        self.name = spec.name
        self.width, self.height = spec.width, spec.height
        self.captures = 0
        self.before_capture = None  # hook(camera) for tests (fill the disk, pull a plug)

    def info(self) -> CameraInfo:
        return CameraInfo(name=self.name, width=self.width, height=self.height, model="synth", white_level=1.0,
                          linear=True)

    def radiance(self) -> np.ndarray:
        rig = self.rig
        h, w = self.height, self.width
        emu = rig.display_emulator
        back = emu.displayed(0, w, h).astype(np.float32) / 255.0  # nearest-scaled, black when blank
        L = back.copy()
        yy, xx = np.mgrid[0:h, 0:w]
        light = sum(rig.dmx_levels().values()) / 255.0
        table = math.radians(rig.table_deg())
        if rig.scene["object"]:
            r = 0.3 * h
            inside = (xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2 <= r * r
            albedo = np.array([0.6, 0.4 + 0.1 * math.cos(table), 0.2 + 0.05 * self.index], np.float32)
            L[inside] = albedo * (0.05 + 0.5 * light)
        if rig.scene["board"]:
            board = ((xx // 3 + yy // 3) % 2).astype(np.float32)[..., None] * (0.1 + 0.4 * light)
            L = np.where((yy > h // 2)[..., None], board, L)
        return L.astype(np.float32)

    def capture(self, exposure_s: float) -> np.ndarray:
        if self.before_capture is not None:
            self.before_capture(self)
        self.rig.settle()
        self.captures += 1
        gain = self.rig.geometry.cameras[self.index].gain
        return np.clip(self.radiance() * gain * exposure_s, 0.0, 1.0).astype(np.float32)


RIG_CONFIG = {
    "rig": {"name": "lab rig (tests)"},
    "devices": {
        "turntable": {"url": "emulator:grbl", "axis": "X", "steps_per_deg": 80.0, "max_rate_deg_s": 90.0,
                      "accel_deg_s2": 180.0, "timeout_s": 2.0},
        "light_array": {"url": "emulator:enttec", "timeout_s": 2.0,
                        "rotation": {"url": "emulator:grbl", "axis": "Y", "steps_per_deg": 80.0,
                                     "max_rate_deg_s": 45.0, "accel_deg_s2": 90.0, "timeout_s": 2.0},
                        "channels": {"0": 1, "1": 2, "2": 3, "3": 4}},
        "backdrops": {"url": "emulator:display", "timeout_s": 1.0, "outputs": {"bottom": 0, "back": 1}},
        "cameras": [{"name": f"cam{i}", "driver": "sim"} for i in range(3)],
    },
    "geometry": GEOMETRY,
}


class LabRig:
    """Implements :class:`opacityhull.rigs.protocols.Rig` with the real drivers and emulators."""

    def __init__(self):
        from opacityhull.rigs.config import parse_rig_config
        from opacityhull.rigs.emulators.launch import start_emulators
        from opacityhull.rigs.rig import build_rig

        config = parse_rig_config(RIG_CONFIG, source="lab-rig")
        self.emulators = start_emulators(config)
        by = self.emulators.by_device
        self.grbl = by["turntable"]
        self.enttec = by["light_array"]
        self.display_emulator = by["backdrops"]
        self.display_server = self.emulators.servers["emulator:display"]
        self.grbl_server = self.emulators.servers["emulator:grbl"]
        self.geometry = config.geometry
        self.cameras = [SynthCamera(self, i) for i in range(len(self.geometry.cameras))]
        self.hw = build_rig(self.emulators.config, cameras=self.cameras, interactive=False, assume_ready=True,
                            reconnect_attempts=1, reconnect_delay_s=0.01)
        self.turntable = self.hw.turntable
        self.light_array = self.hw.light_array
        self.backdrops = self.hw.backdrops
        self.channels = dict(config.light_array.channel_map)
        self.scene = {"board": False, "object": True}
        self.operator_log: list[str] = []
        self.ground_truth_calls: list[list] = []

    # state as the emulators hold it (what a physical camera would see)
    def table_deg(self) -> float:
        return self.grbl.position_deg("X")

    def dmx_levels(self) -> dict[int, int]:
        return {lid: self.enttec.level(ch) for lid, ch in self.channels.items()}

    def settle(self, timeout_s: float = 2.0) -> None:
        """Wait until the lights output what the driver last sent (DMX packets are not
        acknowledged: the bytes may still be in the pty when the shutter opens, as a real
        lamp may still be warming up). A real rig waits a settle time instead."""
        import time

        want = {lid: int(v) for lid, v in self.light_array.levels().items()}
        deadline = time.monotonic() + timeout_s
        while self.dmx_levels() != want and time.monotonic() < deadline:
            time.sleep(0.001)

    def open(self):
        self.hw.open()
        return self

    def close(self):
        try:
            self.hw.close()
        finally:
            self.emulators.stop()

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()
        return False

    def safe(self):
        return self.hw.safe()

    def check(self):
        return self.hw.check()

    def describe(self) -> dict:
        return self.hw.describe()

    def operator(self, action: str, **details):
        self.operator_log.append(action)
        if action == "place_board":
            self.scene["board"] = True
            self.scene["object"] = False
        elif action == "remove_board":
            self.scene["board"] = False
        elif action == "remove_object":
            self.scene["object"] = False
        elif action == "place_object":
            self.scene["object"] = True
        else:
            raise DeviceError(f"unknown operator action {action!r}")

    def ground_truth(self, root, views):
        self.ground_truth_calls.append(list(views))
        d = Path(root) / "groundtruth"
        d.mkdir(exist_ok=True)
        (d / "views.json").write_text(json.dumps([list(v) for v in views]))


def tiny_plan():
    from opacityhull.acquire.plan import parse_plan

    return parse_plan(TINY_PLAN, where="lab-tiny")


def _child(argv):
    """Subprocess entry: capture TINY_PLAN into argv[0], printing ``img <n>`` per image."""
    import signal

    from opacityhull.acquire.runner import run_capture
    from opacityhull.errors import CaptureInterrupted

    out = argv[0]
    resume = "--resume" in argv
    # a slow-ish camera so that a signal lands mid-capture rather than after it
    lock = threading.Lock()

    def progress(done, total):
        with lock:
            sys.stdout.write(f"img {done} {total}\n")
            sys.stdout.flush()

    signal.signal(signal.SIGINT, signal.default_int_handler)
    rig = LabRig()
    rig.open()
    try:
        res = run_capture(rig, tiny_plan(), out, resume=resume, progress=progress, rig_source="lab")
        sys.stdout.write("done " + json.dumps(res.to_dict()) + "\n")
        return 0 if res.complete else 5
    except KeyboardInterrupt:
        rig.settle()
        sys.stdout.write(f"interrupted lights={rig.dmx_levels()} shown={rig.display_emulator.is_lit()} "
                         f"moving={rig.grbl.is_moving} feed_hold_sent={b'!' in rig.grbl.received}\n")
        sys.stdout.flush()
        return 130
    except CaptureInterrupted:
        return 5
    finally:
        rig.close()


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1:]))
