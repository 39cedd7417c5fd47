"""Files ``opacityhull calibrate`` writes: OpenCV FileStorage YAML per camera, a COLMAP text
model (written with pycolmap), the residual histogram and per-frame plot, and the summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..camera import Camera, write_colmap_text, write_opencv_yaml
from ..se3 import invert_rigid
from .run import CalibrateRun

__all__ = ["summary", "write_outputs"]


def summary(run: CalibrateRun) -> dict:
    """The ``--json`` object: cameras in OpenCV's pixel convention (top-left pixel centre
    at 0, 0), with per-parameter standard deviations."""
    res = run.result
    cams = []
    for c, f in sorted(res.cameras.items()):
        src = run.cameras[c].source
        centre = invert_rigid(f.cam_from_world)[:3, 3]
        cams.append(
            {
                "index": c,
                "input": src,
                "width": f.size[0],
                "height": f.size[1],
                "fx": float(f.K[0, 0]),
                "fy": float(f.K[1, 1]),
                "cx": float(f.K[0, 2]),
                "cy": float(f.K[1, 2]),
                "dist": [float(v) for v in f.dist],
                "rms_px": f.rms_px,
                "intrinsic_rms_px": f.intrinsic_rms_px,
                "intrinsic_frames": f.intrinsic_frames,
                # fx = fy tied ("f" free): both carry f's σ, and the aspect is what is held
                "std": f.std | ({"fx": f.std["f"], "fy": f.std["f"]} if "f" in f.std else {}),
                "held": [
                    k
                    for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
                    if k not in f.free and not (k in ("fx", "fy") and "f" in f.free)
                ]
                + (["aspect"] if "f" in f.free else []),
                "frames": f.n_frames,
                "corners": f.n_points,
                "cam_from_world": f.cam_from_world,
                "centre_m": centre,
            }
        )
    return {
        "cameras": cams,
        "board": run.charuco.to_dict() | {"polarity": run.charuco.polarity, "layout": run.charuco.layout},
        "rms_px": res.rms_px,
        "frames_used": len(res.observations),
        "left_out": [{"camera": c, "reason": why} for c, why in sorted(run.left_out.items())],
        "rejected": [r.to_dict() for r in run.rejected],
        "notes": list(run.notes),
        "solver": res.info,
    }


def _plots(run: CalibrateRun, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = run.result
    e = np.linalg.norm(res.residuals_px, axis=1)
    fig, ax = plt.subplots(figsize=(6, 4))
    for c in sorted(res.cameras):
        sel = np.array([res.observations[i].camera == c for i in res.residual_obs])
        ax.hist(e[sel], bins=40, alpha=0.6, label=f"camera {c} (RMS {res.cameras[c].rms_px:.3f} px)")
    ax.set_xlabel("reprojection error (px)")
    ax.set_ylabel("corners")
    ax.set_title("Reprojection error of every corner")
    ax.legend()
    fig.tight_layout()
    p1 = out / "reprojection_histogram.png"
    fig.savefig(p1, dpi=100)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(max(6, 0.08 * len(res.per_frame_rms_px)), 4))
    for c in sorted(res.cameras):
        ys = [res.per_frame_rms_px[o.where] for o in res.observations if o.camera == c]
        ax.plot(range(len(ys)), ys, "o-", ms=3, label=f"camera {c}")
    ax.set_xlabel("frame (in input order, kept frames only)")
    ax.set_ylabel("RMS reprojection error (px)")
    ax.set_title("Per-frame residual")
    ax.legend()
    fig.tight_layout()
    p2 = out / "per_frame_rms.png"
    fig.savefig(p2, dpi=100)
    plt.close(fig)
    return [p1, p2]


def _cameras(run: CalibrateRun) -> list[Camera]:
    return [
        Camera(
            K=f.K,
            dist=f.dist,
            width=f.size[0],
            height=f.size[1],
            world_from_cam=invert_rigid(f.cam_from_world),
            name=f"cam{c}",
        )
        for c, f in sorted(run.result.cameras.items())
    ]


def write_outputs(run: CalibrateRun, out: Path) -> dict[str, str]:
    """Write everything into ``out``; returns what was written (for the summary). The
    COLMAP model (``colmap/``: one camera and one image per calibrated camera, COLMAP's
    principal point = OpenCV's + 0.5) is written by :func:`opacityhull.camera.write_colmap_text`."""
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, str] = {}
    cams = _cameras(run)
    for cam, (c, f) in zip(cams, sorted(run.result.cameras.items()), strict=True):
        p = out / f"cam{c}.yaml"
        write_opencv_yaml(
            p,
            cam,
            extra={
                "avg_reprojection_error": f.rms_px,
                "std_deviations_fx_fy_cx_cy": [f.std.get(k, f.std.get("f", 0.0)) for k in ("fx", "fy")]
                + [f.std.get(k, 0.0) for k in ("cx", "cy")],
            },
        )
        written[f"cam{c}"] = str(p)
    write_colmap_text(out / "colmap", cams)
    written["colmap"] = str(out / "colmap")
    for p in _plots(run, out):
        written[p.stem] = str(p)
    return written
