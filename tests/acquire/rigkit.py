"""A small laboratory rig for the capture tests: the real drivers over ptys to the
real emulators, and a camera that synthesises its image from the emulators' state
(no Mitsuba, so a capture of a few hundred images takes seconds).

The rig itself is published as :class:`opacityhull.rigs.testing.LabRig` (re-exported
here with :class:`~opacityhull.rigs.testing.SynthCamera`, ``GEOMETRY`` and ``RIG_CONFIG``).

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
import sys
import threading

from opacityhull.rigs.testing import LAB_GEOMETRY as GEOMETRY
from opacityhull.rigs.testing import LAB_RIG_CONFIG as RIG_CONFIG
from opacityhull.rigs.testing import LabRig, SynthCamera

__all__ = [
    "GEOMETRY",
    "RIG_CONFIG",
    "TINY_PLAN",
    "LabRig",
    "SynthCamera",
    "assert_left_safe",
    "assert_resumed_to_the_end",
    "tiny_plan",
]

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


def tiny_plan():
    from opacityhull.acquire.plan import parse_plan

    return parse_plan(TINY_PLAN, where="lab-tiny")


def assert_left_safe(report: str) -> None:
    """A capture child's report of the rig after ``rig.safe()`` ran (the line it prints
    when stopped): every light off, no display lit, the table still, a feed hold sent."""
    assert "lights={0: 0, 1: 0, 2: 0, 3: 0}" in report and "shown=False" in report, report
    assert "moving=False" in report and "feed_hold_sent=True" in report, report


def assert_resumed_to_the_end(proc, out, *, listed: int, total: int, timeout_s: float) -> None:
    """``proc``, a capture child started with ``--resume`` on ``out`` where ``listed`` of
    ``total`` images were taken, exits 0 having taken exactly the missing ones; the
    manifest then lists every id once."""
    from opacityhull.session import read_manifest

    rest, err = proc.communicate(timeout=timeout_s)
    assert proc.returncode == 0, err
    res = json.loads([x for x in rest.splitlines() if x.startswith("done ")][0][5:])
    assert res["complete"] and res["taken"] == total - listed
    ids = [r.id for r in read_manifest(f"{out}/manifest.jsonl")]
    assert len(ids) == len(set(ids)) == total


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
        sys.stdout.write(
            f"interrupted lights={rig.dmx_levels()} shown={rig.display_emulator.is_lit()} "
            f"moving={rig.grbl.is_moving} feed_hold_sent={b'!' in rig.grbl.received}\n"
        )
        sys.stdout.flush()
        return 130
    except CaptureInterrupted:
        return 5
    finally:
        rig.close()


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1:]))
