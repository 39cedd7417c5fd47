"""Build step ``write``: the model folder."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Sequence

import numpy as np

from ...errors import FormatError
from ...model import ViewInfo, write_model
from ..buildstore import _digest, _records_digest, cached
from ..lazyviews import _LazyViews, _view_rgba
from ..matte_step import _jsonable
from .base import Step

log = logging.getLogger(__name__)


def _storage_metrics(out: Path, view_ids: Sequence[str], notes: list) -> dict:
    """Pixel type and bytes per view of the written model (read back from the folder, so a
    reused write step reports the same), and the values clamped to the half range (a note
    naming the files: they are not lost silently)."""
    from ...tomlio import read_toml

    meta = read_toml(out / "model.toml", error=FormatError, what="model.toml")
    st = meta.get("storage", {})
    sizes = {}
    for d in ("views", "reflectance"):
        files = [out / d / f"{vid}.exr" for vid in view_ids]
        sizes[d] = sum(f.stat().st_size for f in files if f.is_file()) / max(len(view_ids), 1)
    m = {
        "storage_pixel_type": st.get("pixel_type", "float"),
        "disk_bytes_per_view": sizes["views"] + sizes["reflectance"],
        "disk_bytes_per_view_views": sizes["views"],
        "disk_bytes_per_view_reflectance": sizes["reflectance"],
        "storage_clamped_values": int(st.get("clamped_values", 0)),
    }
    refl = meta.get("reflectance", {})
    if refl.get("present"):
        m["reflectance_storage"] = refl.get("storage", "layers")
    if refl.get("storage") == "pca":
        pv = list(refl.get("pca_views", []))
        m["reflectance_pca"] = {
            "rank": refl.get("pca_rank"),
            "error_target": refl.get("pca_error_target"),
            "block_px": int(refl.get("pca_block", 0)),
            "rank_per_view": {d["id"]: int(d["rank"]) for d in pv},
            "rank_mean_per_view": {d["id"]: float(d.get("rank_mean", d["rank"])) for d in pv},
            "rel_error_per_view": {d["id"]: float(d["rel_error"]) for d in pv},
            "rank_max": int(refl.get("rank_max", 0)),
            "rel_error_max": float(refl.get("rel_error_max", 0.0)),
            # values of the layers / values stored; the bytes: disk_bytes_per_view_reflectance
            "values_ratio": float(refl.get("values_ratio", 1.0)),
        }
    clamped = list(st.get("clamped", []))
    if m["storage_clamped_values"]:
        m["storage_clamped_files"] = clamped
        notes.append(
            f"storage half: {m['storage_clamped_values']} value(s) beyond ±65504 clamped in "
            f"{len(clamped)} file(s): "
            + "; ".join(f"{c['file']} ({c['values']}, max |v| {c['max_abs']:.4g})" for c in clamped[:3])
            + (" ..." if len(clamped) > 3 else "")
            + " (build with --storage float to keep them)"
        )
    return m


@dataclass(frozen=True, kw_only=True)
class WriteProduct:
    """The write step's product: the model's views and provenance, and the step's key."""

    view_infos: list
    provenance: dict
    backdrop_source: str
    key: str


def _model_files(out: Path) -> list[str]:
    """What :func:`~opacityhull.model.write_model` and the rig cameras wrote into ``out``:
    the files a resume must find unchanged to reuse the write step."""
    names = ["model.toml", "surfels.ply", "cameras", "views", "reflectance", "calibration"]
    return [n for n in names if (out / n).exists()]


def run(ctx) -> None:
    session, config, out, cams = ctx.session, ctx.config, ctx.out, ctx.cameras.cams
    views, vids, mattes = ctx.cameras.views, ctx.cameras.vids, ctx.mattes
    g, colour_shots = ctx.geometry.geometry, ctx.holes.colour_shots
    reflectance, refl_digest = ctx.reflectance
    natural, natural_key = ctx.natural
    split = ctx.split
    alphas = mattes.alphas
    view_infos = [ViewInfo(i, vids[i], c, float(a), cams.views[i]) for i, (c, a) in enumerate(views)]
    backdrop_source = ", ".join(sorted(mattes.sources))
    provenance = {
        "session": str(session.root.resolve()),
        "rig_source": session.source,
        "camera_source": cams.source,
        "backdrop_source": backdrop_source,
        "reflectance_units": "radiance at full DMX level (one-light images scaled by 255/level)",
        # a TOML table (model.py: build_config_none); without the optimize step's options, which
        # do not shape the written model (a resume with another --optimize reuses the write)
        "build_config": _jsonable(
            {k: v for k, v in config.to_dict().items() if k not in ("optimize", "optimize_iterations")}
        ),
    }
    write_in = {
        "geometry": ctx.geometry.key,
        "mattes": mattes.content,
        "cameras": ctx.cameras.key,
        "natural": natural_key,
        "colour": _digest(
            [
                _records_digest(session, session.select(shot=s, kind=None))
                for pair in colour_shots
                for s in pair
                if s is not None
            ]
        ),
        "reflectance": refl_digest,
        "provenance": _digest(provenance),
        **({"held_out": list(split.held_out)} if split.held_out else {}),
    }

    def view_rgba(i: int) -> np.ndarray:
        from ..liveviews import LIVE_VIEWS

        return LIVE_VIEWS.track(
            vids[i],
            _view_rgba(
                session,
                colour_shots[i],
                alphas[i],
                use_masks=mattes.use_masks,
                alpha_eps=config.alpha_eps,
                finite=lambda img, where: ctx.finite(img, f"view {vids[i]} {where.removeprefix('view ')}"),
            ),
        )

    def write() -> None:
        out.mkdir(parents=True, exist_ok=True)
        # an earlier model's model.toml would make a half-rewritten folder look finished
        (out / "model.toml").unlink(missing_ok=True)
        extra = None
        if natural is not None:
            extra = {} if extra is None else extra
            extra |= {
                "natural": {
                    "present": True,
                    "format": "opacityhull.natural/1",
                    "dir": "natural",
                    "n_kernels": int(natural["n_kernels"]),
                    "weights_dtype": str(natural.get("weights_dtype", "float16")),
                    "displays": {
                        n: {"domain_hw": list(d["domain_hw"]), "images": int(d["images"])}
                        for n, d in natural["displays"].items()
                    },
                }
            }
        if split.held_out:
            # test views: on record (camera, photograph), kept out of the geometry and blending
            extra = {} if extra is None else extra
            extra["split"] = {
                "hold_out": str(split.spec),
                "held_out": [vids[i] for i in split.held_out],
                "train": len(split.train),
            }
        if cams.rig:
            from ...camera import write_opencv_yaml

            for i, rc in enumerate(cams.rig):
                if rc is None:
                    continue
                yx = {"reproj_rms_px": cams.rms_px[i]} if i in cams.rms_px else None
                name = session.geometry.cameras[i].name if i < len(session.geometry.cameras) else f"cam{i}"
                write_opencv_yaml(out / "calibration" / f"{name}.yaml", rc.with_name(name), extra=yx)
        write_model(
            out,
            views=view_infos,
            surfels=g.surfels,
            view_rgba=_LazyViews(view_rgba, len(views)),
            rig=session.meta.get("rig"),
            provenance=provenance,
            reflectance=reflectance,
            extra_meta=extra,
            progress=ctx.progress,
            storage=config.storage,
            reflectance_storage=config.reflectance_storage,
            pca_rank=config.pca_rank,
            pca_error=config.pca_error,
            pca_block=config.pca_block,
        )

    with ctx.timer.step("write"):
        got = cached(ctx.store, "write", inputs=write_in, params={}, run=write, outputs=lambda _: _model_files(out))
    ctx.model = WriteProduct(view_infos=view_infos, provenance=provenance, backdrop_source=backdrop_source, key=got.key)


STEP = Step(
    name="write",
    run=run,
    inputs=("session", "cameras", "split", "mattes", "holes", "geometry", "reflectance", "natural", "config", "store"),
    product="model",
    params=("storage", "reflectance_storage", "pca_rank", "pca_error", "pca_block", "alpha_eps"),
)
