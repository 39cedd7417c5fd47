"""CLI command ``opacityhull calibrate`` (registered by :mod:`opacityhull.cli`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from ..cliutil import JsonFlag, cli_errors, console, emit, writing_to

__all__ = ["register"]

_BOARD_HELP = (
    "Board spec: a TOML file, or key=value pairs mirroring OpenCV's names: "
    "squares=5x7,square_m=0.04,marker_m=0.02,dictionary=DICT_6X6_250[,polarity=auto|normal|inverted]"
    "[,layout=auto|new|legacy]. caliscope's charuco.toml is read as it is."
)
_INPUTS_HELP = (
    "Board photographs (together one camera), or one video or image directory per camera. Frame k of every "
    "video (or same-named images across directories) is one instant unless --sync says otherwise."
)
_SYNC_HELP = (
    "CSV with columns sync_index,cam_id,frame_index[,frame_time] (caliscope's timestamps.csv): which video "
    "frames are the same instant; cam_id = the video's position among the inputs."
)


def _human(s: dict) -> None:
    from rich.markup import escape
    from rich.table import Table

    c = console()
    t = Table(title=f"calibration: {s['frames_used']} frames, RMS {s['rms_px']:.3f} px")
    for col in ("camera", "fx ± σ", "fy ± σ", "cx ± σ", "cy ± σ", "RMS px", "alone px", "frames"):
        t.add_column(col, justify="right")
    for cam in s["cameras"]:
        sd = cam["std"]

        def pm(k, cam=cam, sd=sd):
            return f"{cam[k]:.2f} ± {sd.get(k, sd.get('f', 0.0)) if k in ('fx', 'fy') else sd.get(k, 0.0):.2f}"

        t.add_row(
            str(cam["index"]),
            pm("fx"),
            pm("fy"),
            pm("cx"),
            pm("cy"),
            f"{cam['rms_px']:.3f}",
            f"{cam['intrinsic_rms_px']:.3f}",
            str(cam["frames"]),
        )
    c.print(t)
    for lo in s["left_out"]:
        c.print(f"[yellow]left out:[/] {escape(lo['reason'])}")
    for n in s["notes"]:
        c.print(f"[yellow]note:[/] {escape(n)}")
    c.print(f"{len(s['rejected'])} frame(s) rejected (see rejected.json)")
    for k, v in s.get("outputs", {}).items():
        c.print(f"{k}: {v}", markup=False)


def register(app, groups) -> None:
    """Add ``calibrate`` to the root app."""

    @app.command("calibrate")
    @cli_errors
    def calibrate(
        inputs: Annotated[list[Path], typer.Argument(help=_INPUTS_HELP)],
        board: Annotated[str, typer.Option("--board", help=_BOARD_HELP)],
        out: Annotated[Path | None, typer.Option("--out", help="Folder for YAML, COLMAP, plots, report.")] = None,
        sync: Annotated[Path | None, typer.Option("--sync", help=_SYNC_HELP)] = None,
        dist: Annotated[str, typer.Option("--dist", help="Distortion model: none|k1|k1k2|k1k2p|k1k2pk3.")] = "k1k2pk3",
        every: Annotated[int, typer.Option("--every", help="Use every Nth video frame.")] = 1,
        min_corners: Annotated[int, typer.Option("--min-corners", help="Frames with fewer corners are dropped.")] = 6,
        blur_ratio: Annotated[
            float, typer.Option("--blur-ratio", help="Drop frames sharper than this x the camera's median (0: keep).")
        ] = 0.35,
        max_skew: Annotated[
            float,
            typer.Option(
                "--max-skew",
                help="With --sync frame_time: instants whose frames lie further apart (s) calibrate "
                "each camera's intrinsics only.",
            ),
        ] = 0.005,
        refine_intrinsics: Annotated[
            bool, typer.Option("--refine-intrinsics", help="Free the intrinsics in the multi-camera bundle adjustment.")
        ] = False,
        intrinsics: Annotated[
            list[Path] | None,
            typer.Option(
                "--intrinsics",
                help="OpenCV YAML (camera_matrix, distortion_coefficients) of a camera, in input order, "
                "to hold its intrinsics as given (e.g. from `calibrate` on its own video); repeat per camera.",
            ),
        ] = None,
        interpolate: Annotated[
            str,
            typer.Option(
                "--interpolate",
                help="How ChArUco corners are placed before sub-pixel refinement: aruco-calib (OpenCV's "
                "calibrate_camera_charuco sample: through a first calibration from the marker corners) or "
                "homography (OpenCV's CharucoDetector alone, one decoding pass).",
            ),
        ] = "aruco-calib",
        fix_principal_point: Annotated[
            bool,
            typer.Option("--fix-principal-point", help="Hold cx, cy at the image centre (CALIB_FIX_PRINCIPAL_POINT)."),
        ] = False,
        fix_aspect_ratio: Annotated[
            bool, typer.Option("--fix-aspect-ratio", help="Hold fx = fy (CALIB_FIX_ASPECT_RATIO).")
        ] = False,
        as_json: JsonFlag = False,
    ):
        """Calibrate cameras from ChArUco photographs or videos: intrinsics, distortion,
        and (several synchronised cameras) their poses by bundle adjustment."""
        from ..errors import InputError
        from .inputs import parse_board
        from .outputs import summary, write_outputs
        from .run import CalibrateOptions, calibrate_cameras

        spec = parse_board(board)
        if out is not None and out.exists() and not out.is_dir():
            raise InputError(f"--out {out}: is an existing file, expected a folder")
        held = []
        for i, p in enumerate(intrinsics or []):
            from ..camera import read_opencv_yaml

            if not p.is_file():
                raise InputError(f"--intrinsics {p}: no such file")
            cam = read_opencv_yaml(p)
            held.append((i, cam.K, cam.dist, (cam.width, cam.height), str(p)))
        opts = CalibrateOptions(
            intrinsics=tuple(held),
            dist_model=dist,
            min_corners=min_corners,
            blur_ratio=blur_ratio,
            step=every,
            max_skew_s=max_skew,
            refine_intrinsics=refine_intrinsics,
            interpolate=interpolate,  # pyright: ignore[reportArgumentType]  (checked by CalibrateOptions)
            fix_principal_point=fix_principal_point,
            fix_aspect_ratio=fix_aspect_ratio,
        )
        run = calibrate_cameras(list(inputs), charuco=spec, sync=sync, options=opts)
        s = summary(run)
        if out is not None:
            with writing_to(out):
                s["outputs"] = write_outputs(run, out)
                (out / "rejected.json").write_text(json.dumps(s["rejected"], indent=1) + "\n")
                from ..jsonio import to_jsonable

                (out / "calibration.json").write_text(json.dumps(to_jsonable(s), indent=1) + "\n")
        emit(s, as_json, _human)
