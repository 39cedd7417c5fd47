"""``opacityhull calibrate``: intrinsics, distortion and poses of a user's own cameras from
ChArUco photographs or videos (:mod:`.inputs` frames and the rejection report,
:mod:`.bundle` the per-camera initialisation and the bundle adjustment, :mod:`.run` the
runner, :mod:`.outputs` YAML / COLMAP / plots / summary, :mod:`.commands` the CLI)."""
