"""Turntable calibration with the two ChArUco corner interpolations (issue #31):
``CalibrationConfig.interpolate`` = ``homography`` (one pass) against ``aruco-calib``
(corners re-found through a first calibration from the marker corners, as
``opacityhull calibrate`` does), on the Mitsuba-simulated rig.

For the built-in tiny and demo plans (200x150 cameras) and the demo plan at twice the
resolution, the plan's calibration phase alone is captured on ``sim:builtin:diffuse``
(the same board shots as the whole plan: the tiny plan's homography figures are those
``build --ground-truth`` prints for it, 50.1 mm and 5.1 %) and calibrated both ways.
The renders do not depend on the plan's seed (seeds 7/8 and 11/12 gave identical
figures), so one session per plan and scale. the errors are those
``build --ground-truth`` reports (``pose_errors`` in the true frame:
``pose_max_position_mm``, ``pose_max_focal_pct``, ``pose_max_rotation_deg``; the
gauge-aligned ones; ``max_volume_reproj_px``, the working volume's reprojection
difference from the true cameras, what silhouettes and hulls see), plus the
reprojection RMS.

    .venv/bin/python benchmarks/turntable_interpolation.py [--quick] [--json]

Writes ``benchmarks/out/turntable_interpolation.{md,json}``. ``--quick``: the
200x150 sessions only.
"""

from __future__ import annotations

import json
import sys
import tempfile
import tomllib
from pathlib import Path

from benchkit import out_dir, parser

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()
sys.path.insert(0, str(ROOT))

from opacityhull.reconstruct.calibration import Interpolation  # noqa: E402

MODES: tuple[Interpolation, ...] = ("homography", "aruco-calib")


def capture_calibration(plan_name: str, scale: float, out: Path) -> Path:
    """The calibration phase of builtin ``plan_name`` captured to ``out`` at ``scale``
    times the simulated cameras' 200x150."""
    from opacityhull.acquire.plan import parse_plan
    from opacityhull.acquire.runner import run_capture
    from opacityhull.sim.simrig import open_sim_rig

    d = tomllib.loads((ROOT / "opacityhull" / "acquire" / "plans" / f"{plan_name}.toml").read_text())
    d["phases"] = {"calibration": d["phases"]["calibration"]}
    with open_sim_rig(f"sim:builtin:diffuse?scale={scale:g}") as rig:
        run_capture(rig, parse_plan(d), out, fsync=False)
        rig.ground_truth(out, [])
    return out


def measure(session_dir: Path, mode: Interpolation) -> dict:
    from opacityhull.camera import read_opencv_yaml
    from opacityhull.reconstruct.calibration import CalibrationConfig, calibrate_session, pose_errors
    from opacityhull.session import Session

    s = Session.open(session_dir)
    true = [
        read_opencv_yaml(session_dir / "groundtruth" / "calibration" / f"{c.name}.yaml") for c in s.geometry.cameras
    ]
    # as the build calls it (skip_unusable_cameras=drop_uncalibrated is on for `build`)
    res = calibrate_session(s, config=CalibrationConfig(skip_unusable_cameras=True, interpolate=mode))
    pe = pose_errors(res, true, align_gauge=False)
    pg = pose_errors(res, true, align_gauge=True)
    return {
        "cameras": list(res.camera_indices),
        "rms_px": float(res.rms_px),
        "max_rms_px": max(float(res.reproj_rms_px[c]) for c in res.camera_indices),
        "pose_max_position_mm": pe["max_position_mm"],
        "pose_max_focal_pct": pe["max_focal_pct"],
        "pose_max_rotation_deg": pe["max_rotation_deg"],
        "gauge_aligned_max_position_mm": pg["max_position_mm"],
        "gauge_aligned_max_rotation_deg": pg["max_rotation_deg"],
        "max_volume_reproj_px": pg["max_volume_reproj_px"],
        "seconds_detect": res.seconds.get("detect"),
    }


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="the 200x150 sessions only")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON on stdout")
    args = ap.parse_args()
    runs = [("tiny", 1.0), ("demo", 1.0)] + ([] if args.quick else [("demo", 2.0)])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for plan, scale in runs:
            sess = capture_calibration(plan, scale, Path(tmp) / f"{plan}_{scale:g}")
            for mode in MODES:
                r = {"plan": plan, "scale": scale, "interpolate": mode, **measure(sess, mode)}
                print(json.dumps(r), file=sys.stderr)
                rows.append(r)
    keys = [
        "rms_px",
        "pose_max_position_mm",
        "pose_max_focal_pct",
        "pose_max_rotation_deg",
        "gauge_aligned_max_position_mm",
        "gauge_aligned_max_rotation_deg",
        "max_volume_reproj_px",
    ]
    lines = [
        "# Turntable calibration: homography vs aruco-calib corner interpolation",
        "",
        "Simulated rig (sim:builtin:diffuse), the plan's calibration phase; errors as `build --ground-truth`.",
        "",
        "| plan | scale | interpolate | cameras | " + " | ".join(keys) + " |",
        "|" + "---|" * (4 + len(keys)),
    ]
    for r in rows:
        lines.append(
            f"| {r['plan']} | {r['scale']:g} | {r['interpolate']} | {r['cameras']} | "
            + " | ".join(f"{r[k]:.3f}" for k in keys)
            + " |"
        )
    (OUT / "turntable_interpolation.md").write_text("\n".join(lines) + "\n")
    (OUT / "turntable_interpolation.json").write_text(json.dumps(rows, indent=1))
    print(json.dumps(rows) if args.json else "\n".join(lines))


if __name__ == "__main__":
    main()
