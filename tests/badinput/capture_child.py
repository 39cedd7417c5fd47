"""Subprocess entry of the signal tests: ``python capture_child.py OUT [--resume]``.

Captures the lab rig's tiny plan (tests/acquire/rigkit.py: real drivers over ptys to the
emulators, a synthetic camera) through the CLI's own error handling (``cli_errors``), so
the exit code is the one ``opacityhull capture`` gives. Prints ``img <n>`` per image and,
however the capture ends, the rig state after ``rig.safe()`` ran.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "acquire"))


def main(argv) -> int:
    import typer

    from opacityhull.acquire.runner import run_capture
    from opacityhull.cliutil import cli_errors
    from rigkit import LabRig, tiny_plan

    out = argv[0]
    resume = "--resume" in argv
    rig = LabRig()
    rig.open()

    import os
    import time

    hold = os.environ.get("OPACITYHULL_TEST_HOLD_AT")

    def progress(done, total):
        sys.stdout.write(f"img {done} {total}\n")
        sys.stdout.flush()
        if hold and done == int(hold.split(":")[0]):
            # wait for the parent to have sent its signal (it then creates the marker),
            # so the signal always lands mid-capture however loaded the machine is
            mark = Path(hold.split(":", 1)[1])
            for _ in range(3000):
                if mark.exists():
                    break
                time.sleep(0.02)

    @cli_errors
    def capture():
        try:
            res = run_capture(rig, tiny_plan(), out, resume=resume, progress=progress, rig_source="lab")
            sys.stdout.write("done " + json.dumps(res.to_dict()) + "\n")
        finally:
            rig.settle()
            sys.stdout.write(
                f"state lights={rig.dmx_levels()} shown={rig.display_emulator.is_lit()} "
                f"moving={rig.grbl.is_moving} feed_hold_sent={b'!' in rig.grbl.received}\n"
            )
            sys.stdout.flush()

    try:
        capture()
        return 0
    except typer.Exit as e:
        return e.exit_code
    finally:
        rig.close()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
