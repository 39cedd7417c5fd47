"""Issue #35 (and #33's imports): no command writes over what it reads, damaged files are
named, and the messages speak in flags. Every case checks the sha256 of the inputs
before and after (badkit.run_case): nothing captured or computed is lost."""

from __future__ import annotations

import json
import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from badkit import Case, flat, invoke, run_case, tree_digest

# ----------------------------------------------------------------------------- setups


def _rgb_jpeg(root: Path, name: str, seed: int, *, truncate: bool = False) -> None:
    import cv2

    img = (np.random.default_rng(seed).random((24, 32, 3)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    b = buf.tobytes()
    (root / name).write_bytes(b[: len(b) // 2] if truncate else b)


def _matte_inputs(truncate_first: bool):
    def setup(root: Path) -> None:
        for k in range(2):
            _rgb_jpeg(root, f"obj{k}.jpg", k, truncate=truncate_first and k == 0)
            _rgb_jpeg(root, f"back{k}.jpg", 10 + k)

    return setup


def _jpeg_as_hdr(root: Path) -> None:
    _rgb_jpeg(root, "probe.hdr", 3)


def _write(name: str, text: str):
    def setup(root: Path) -> None:
        (root / name).write_text(text)

    return setup


BOGUS_DICT_PLAN = """
[plan]
name = "p"
[table]
steps = 2
[phases.calibration]
charuco = { dictionary = "DICT_BOGUS" }
[phases.matting]
patterns = 1
"""

NO_CAMERAS = """
[geometry]
target_m = [0.0, 0.1, 0.0]
cameras = []
"""

# --------------------------------------------------------------------- item 1: outputs


OUTPUT_CASES = [
    Case(
        "export-out-is-the-model-overwrite",
        ("export", "{M}", "--format", "ply", "--out", "{M}", "--overwrite"),
        2,
        r"--out .*: is the input MODEL",
    ),
    Case(
        "export-out-contains-the-model",
        ("export", "{M}", "--format", "ply", "--out", "{T}", "--overwrite"),
        2,
        r"--out .*: contains the input MODEL .* replacing --out would delete it",
    ),
    Case(
        "export-out-inside-the-model",
        ("export", "{M}", "--format", "ply", "--out", "{M}/views", "--overwrite"),
        2,
        r"--out .*/views: is inside the input MODEL",
    ),
    Case("view-out-is-the-model", ("view", "{M}", "--out", "{M}"), 2, r"--out .*: is the input MODEL"),
    Case(
        "render-out-inside-the-model",
        ("render", "{M}", "--out", "{M}/views/c0_t000.000.exr"),
        2,
        r"--out .*c0_t000.000.exr: is inside the input MODEL",
    ),
    Case(
        "render-orbit-out-inside-the-model",
        ("render", "{M}", "--orbit", "2", "--out", "{M}/frames/o.png"),
        2,
        r"is inside the input MODEL",
        must_not_exist=("{M}/frames",),
    ),
    Case(
        "eval-loo-out-is-the-model",
        ("eval", "loo", "{M}", "--views", "0", "--out", "{M}"),
        2,
        r"--out .*: is the input MODEL",
    ),
]


@pytest.mark.parametrize("case", OUTPUT_CASES, ids=[c.id for c in OUTPUT_CASES])
def test_no_command_writes_over_its_input(case, model_dir, tmp_path):
    run_case(case, inputs={"M": model_dir}, tmp_path=tmp_path)


def test_relight_out_is_the_model(relight_model_dir, tmp_path):
    case = Case(
        "relight-out-is-the-model",
        ("relight", "{M}", "--out", "{M}", "--envmap", "builtin:grace", "--no-views"),
        2,
        r"--out .*: is the input MODEL",
    )
    run_case(case, inputs={"M": relight_model_dir}, tmp_path=tmp_path)


def test_build_out_is_the_session(session_dir, tmp_path):
    case = Case("build-out-is-the-session", ("build", "{S}", "--out", "{S}"), 2, r"--out .*: is the session folder")
    run_case(case, inputs={"S": session_dir}, tmp_path=tmp_path)


def test_import_out_inside_its_images(model_dir, tmp_path):
    ex = tmp_path / "ns"
    assert invoke(["export", model_dir, "--format", "nerfstudio", "--out", ex]).exit_code == 0
    before = tree_digest(ex)
    r = invoke(["import", "nerfstudio", "--transforms", ex / "transforms.json", "--out", ex / "session"])
    assert r.exit_code == 2 and "is inside the input --transforms' folder" in flat(r.stderr), r.output
    assert tree_digest(ex) == before and not (ex / "session").exists()


def test_capture_out_is_the_plan(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text((Path(__file__).resolve().parents[2] / "tests/e2e/data/sim_ci.toml").read_text())
    before = plan.read_bytes()
    r = invoke(["capture", "--rig", "sim:builtin:diffuse", "--plan", plan, "--out", plan])
    assert r.exit_code == 2 and "is the input --plan" in flat(r.stderr), r.output
    assert plan.read_bytes() == before


def test_matte_out_over_an_input_photograph(tmp_path):
    _matte_inputs(False)(tmp_path)
    shutil.copy(tmp_path / "obj0.jpg", tmp_path / "alpha.png")  # a photograph that happens to be called alpha.png
    before = tree_digest(tmp_path)
    r = invoke(
        ["matte", "--out", tmp_path, "--object", tmp_path / "obj0.jpg", tmp_path / "obj1.jpg"]
        + ["--over", tmp_path / "alpha.png", "--backdrop", tmp_path / "back0.jpg", tmp_path / "back1.jpg"]
    )
    assert r.exit_code == 2 and "alpha.png would be written over the input --over" in flat(r.stderr), r.output
    assert tree_digest(tmp_path) == before


def test_overwrite_replaces_only_the_commands_own_output(model_dir, tmp_path):
    """`--overwrite` replaces an earlier export (its written-files list) and nothing else."""
    out = tmp_path / "ply"
    assert invoke(["export", model_dir, "--format", "ply", "--out", out]).exit_code == 0
    assert json.loads((out / ".opacityhull-written.json").read_text())["command"] == "export"
    r = invoke(["export", model_dir, "--format", "ply", "--out", out, "--overwrite"])
    assert r.exit_code == 0, r.output  # its own earlier output: replaced
    (out / "notes.txt").write_text("mine\n")  # the user's file among the export's
    before = tree_digest(out)
    r = invoke(["export", model_dir, "--format", "ply", "--out", out, "--overwrite"])
    assert r.exit_code == 2 and "notes.txt" in flat(r.stderr) and "not its own" in flat(r.stderr), r.output
    assert tree_digest(out) == before
    other = tmp_path / "other"
    other.mkdir()
    (other / "thesis.tex").write_text("x")
    r = invoke(["export", model_dir, "--format", "ply", "--out", other, "--overwrite"])
    assert r.exit_code == 2 and "no record of one" in flat(r.stderr), r.output
    assert (other / "thesis.tex").read_text() == "x"


# ----------------------------------------------------------------------- items 4-14


def test_render_height_alone_keeps_the_aspect(model_dir, tmp_path):
    """Item 4: the size check assumed the default width with --height alone (MemoryError)."""
    case = Case(
        "render-height-huge",
        ("render", "{M}", "--view", "2,90", "--height", "100000", "--out", "{T}/o.png"),
        2,
        r"--width/--height: 133333 x 100000 = 13333 Mpx is more than",
        must_not_exist=("{T}/o.png",),
    )
    run_case(case, inputs={"M": model_dir}, tmp_path=tmp_path)


def _bin_model(tmp_path: Path, model_dir: Path) -> tuple[Path, Path]:
    ex = tmp_path / "colmap"
    r = invoke(["export", model_dir, "--format", "colmap", "--out", ex])
    assert r.exit_code == 0, r.output
    return ex / "sparse" / "0", ex / "images"


@pytest.mark.parametrize(
    "name, cut, message",
    [
        ("cameras.bin", 8, r"cameras.bin: truncated at camera record 2 .*PINHOLE: 4 parameters = 32 bytes"),
        ("cameras.bin", 16, r"cameras.bin: truncated at camera record 2"),
        ("cameras.bin", 40, r"cameras.bin: truncated at camera record 2: the format needs 24 more byte"),
        ("images.bin", 100, r"images.bin: image record 11 \(id 12\) lists \d+ points2D"),
        ("points3D.bin", None, r"points3D.bin: \d+ points3D recorded, which needs at least \d+ bytes"),
    ],
)
def test_import_colmap_binary_checks_sizes(model_dir, tmp_path, name, cut, message):
    """Item 6: pycolmap does not check EOF (garbage intrinsics, exit 0; 98 s to bad_alloc)."""
    sparse, images = _bin_model(tmp_path, model_dir)
    p = sparse / name
    b = p.read_bytes()
    p.write_bytes(b[: len(b) // 2] if cut is None else b[:-cut])
    case = Case(
        f"colmap-{name}",
        ("import", "colmap", "--model", str(sparse), "--images", str(images), "--out", "{T}/s"),
        4,
        message,
        must_not_exist=("{T}/s",),
    )
    run_case(case, inputs={}, tmp_path=tmp_path / "run")


def test_import_nerfstudio_duplicate_frame_with_another_pose(model_dir, tmp_path):
    """Item 7: two frames of one file_path with different poses imported with exit 0."""
    ex = tmp_path / "ns"
    assert invoke(["export", model_dir, "--format", "nerfstudio", "--out", ex]).exit_code == 0
    t = json.loads((ex / "transforms.json").read_text())
    dup = json.loads(json.dumps(t["frames"][0]))
    dup["transform_matrix"][0][3] += 0.05
    t["frames"].append(dup)
    (ex / "transforms.json").write_text(json.dumps(t))
    before = tree_digest(ex)
    r = invoke(["import", "nerfstudio", "--transforms", ex / "transforms.json", "--out", tmp_path / "s"])
    assert r.exit_code == 4, r.output
    assert re.search(r"frames 0 and \d+ both use the image .* with different cameras", flat(r.stderr)), r.stderr
    assert tree_digest(ex) == before and not (tmp_path / "s").exists()


MATTE = ("matte", "--out", "{T}/m", "--object", "{T}/obj0.jpg", "{T}/obj1.jpg")
MATTE_B = ("--backdrop", "{T}/back0.jpg", "{T}/back1.jpg")

FILE_CASES = [
    # item 8: 98 % unknown, exit 0, only libjpeg's line
    Case(
        "matte-truncated-jpeg",
        MATTE + MATTE_B,
        2,
        r"--object .*obj0.jpg: not a readable image \(.*truncated JPEG \(\d+ bytes, no end-of-image marker\)",
        setup=_matte_inputs(True),
        must_not_exist=("{T}/m",),
    ),
    # item 10: the dry run blessed what the capture refused after writing session.toml
    Case(
        "dry-run-bogus-dictionary",
        ("capture", "--rig", "sim:builtin:diffuse", "--plan", "{T}/plan.toml", "--dry-run"),
        2,
        r"plan.toml: \[phases.calibration\].charuco.dictionary: unknown ArUco dictionary 'DICT_BOGUS'",
        setup=_write("plan.toml", BOGUS_DICT_PLAN),
    ),
    Case(
        "capture-bogus-dictionary-writes-nothing",
        ("capture", "--rig", "sim:builtin:diffuse", "--plan", "{T}/plan.toml", "--out", "{T}/s"),
        2,
        r"plan.toml: .*charuco.dictionary: unknown ArUco dictionary",
        setup=_write("plan.toml", BOGUS_DICT_PLAN),
        must_not_exist=("{T}/s",),
    ),
    Case(
        "dry-run-unknown-sim-scene",
        ("capture", "--rig", "sim:builtin:nosuch", "--plan", "builtin:tiny", "--dry-run"),
        2,
        r"no built-in scene 'nosuch'",
    ),
    # message: the TOML table name was garbled as [[rigs/nocams.toml: geometry.cameras]]
    Case(
        "no-cameras-table-name",
        ("capture", "--rig", "{T}/nocams.toml", "--plan", "builtin:tiny", "--dry-run"),
        2,
        r"nocams.toml: geometry.cameras: at least one \[\[geometry.cameras\]\] entry is required",
        setup=_write("nocams.toml", NO_CAMERAS),
    ),
]


@pytest.mark.parametrize("case", FILE_CASES, ids=[c.id for c in FILE_CASES])
def test_bad_files_are_named(case, tmp_path):
    run_case(case, inputs={}, tmp_path=tmp_path)


def test_relight_envmap_jpeg_renamed_hdr(relight_model_dir, tmp_path):
    """Item 9: 8-bit pixels were taken as radiance (exit 0); and no raw OpenCV line."""
    _jpeg_as_hdr(tmp_path)
    case = Case(
        "relight-jpeg-as-hdr",
        ("relight", "{M}", "--out", "{T}/r", "--envmap", "{T}/probe.hdr", "--no-views"),
        4,
        r"probe.hdr: not a Radiance .hdr file \(it starts with b'\\xff\\xd8",
        must_not_exist=("{T}/r/relight.json",),
    )
    run_case(case, inputs={"M": relight_model_dir}, tmp_path=tmp_path)


def test_workers_zero(session_dir, tmp_path):
    """Item 11: --workers 0 ran with the core count (-3 was refused)."""
    case = Case(
        "build-workers-zero",
        ("build", "{S}", "--out", "{T}/m", "--scheduler", "threads", "--workers", "0"),
        2,
        r"--workers 0: expected at least 1",
        must_not_exist=("{T}/m",),
    )
    run_case(case, inputs={"S": session_dir}, tmp_path=tmp_path)


MISSING_CASES = [
    Case("export-missing-model", ("export", "{T}/nosuch", "--format", "ply", "--out", "{T}/o"), 2, r"nosuch: no such"),
    Case("view-missing-model", ("view", "{T}/nosuch", "--out", "{T}/o"), 2, r"nosuch: no such model folder"),
]


@pytest.mark.parametrize("case", MISSING_CASES, ids=[c.id for c in MISSING_CASES])
def test_missing_paths_are_bad_input(case, tmp_path):
    """Item 14: a missing path was exit 4 (corrupt)."""
    run_case(case, inputs={}, tmp_path=tmp_path)


def test_relight_missing_envmap_names_the_flag(relight_model_dir, tmp_path):
    case = Case(
        "relight-missing-envmap",
        ("relight", "{M}", "--out", "{T}/r", "--envmap", "{T}/nosuch.hdr", "--no-views"),
        2,
        r"--envmap .*nosuch.hdr: no such file",
    )
    run_case(case, inputs={"M": relight_model_dir}, tmp_path=tmp_path)


# ------------------------------------------------------------------------ messages


def test_no_emoji_from_user_values(model_dir, tmp_path):
    case = Case(
        "view-smile",
        ("render", "{M}", "--view", "0,:smile:", "--out", "{T}/o.png"),
        2,
        r"--view '0,:smile:': expected CAM,TABLE_DEG",
    )
    r = run_case(case, inputs={"M": model_dir}, tmp_path=tmp_path)
    assert "😄" not in r.stderr


BUILD_FLAG_CASES = [
    (("--hull-res", "1"), r"--hull-res must be in \[4, 2048\]"),
    (("--bounds", "0,0,0,0,0,0"), r"--bounds must be"),
    (("--alpha-threshold", "2"), r"--alpha-threshold must be in \[0, 1\)"),
    (("--carve-tolerance", "-1"), r"--carve-tolerance must be"),
    (("--exclude-view", "nosuch"), r"--exclude-view: \['nosuch'\] are not views of"),
]


@pytest.mark.parametrize("flags, message", BUILD_FLAG_CASES, ids=[f[0] for f, _ in BUILD_FLAG_CASES])
def test_build_messages_name_flags_not_fields(session_dir, tmp_path, flags, message):
    case = Case(f"build{flags[0]}", ("build", "{S}", "--out", "{T}/m", *flags), 2, message)
    r = run_case(case, inputs={"S": session_dir}, tmp_path=tmp_path)
    for field in ("hull_res", "bounds_m", "alpha_threshold", "carve_tolerance", "exclude_views"):
        assert field not in r.stderr


def test_render_k_names_the_flag(model_dir, tmp_path):
    case = Case(
        "render-k-zero", ("render", "{M}", "--k", "0", "--out", "{T}/o.png"), 2, r"--k = 0: expected an integer"
    )
    r = run_case(case, inputs={"M": model_dir}, tmp_path=tmp_path)
    assert "RenderConfig" not in r.stderr


def test_damaged_exr_gives_one_clean_line(model_dir, tmp_path):
    """OpenEXR's EXR_ERR_BAD_CHUNK_LEADER lines came before the clean error (a subprocess:
    pytest's own capture would hide where the binding's prints go)."""
    import subprocess
    import sys

    m = tmp_path / "M"
    shutil.copytree(model_dir, m)
    v = sorted((m / "views").glob("*.exr"))[0]
    b = v.read_bytes()
    v.write_bytes(b[: len(b) // 2])
    r = subprocess.run(
        [sys.executable, "-m", "opacityhull.cli", "render", str(m), "--out", str(tmp_path / "o.png")],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 4, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:") and "EXR_ERR_" in lines[0], r.stderr
    assert r.stdout == ""


def test_damaged_hdr_gives_no_opencv_line(tmp_path, capfd):
    from opacityhull.errors import FormatError
    from opacityhull.imageio import read_hdr, write_hdr

    p = tmp_path / "a.hdr"
    write_hdr(p, np.ones((8, 16, 3), np.float32))
    p.write_bytes(p.read_bytes()[:-40])
    capfd.readouterr()
    with pytest.raises(FormatError, match=r"a.hdr: not a readable Radiance .hdr file \(truncated or damaged"):
        read_hdr(p)
    out, err = capfd.readouterr()
    assert "[ERROR:" not in out + err


def test_write_errors_advise_by_cause():
    """A read-only disk advised "free space"; an unnamed path said "cannot write None"."""
    import errno

    from opacityhull.errors import write_error

    ro = write_error(OSError(errno.EROFS, "Read-only file system", "/mnt/x"))
    assert ro is not None and "read-only" in str(ro) and "free space" not in str(ro) and "remount" in str(ro)
    full = write_error(OSError(errno.ENOSPC, "No space left on device"))
    assert full is not None and "None" not in str(full) and "free space" in str(full)


# ------------------------------------------------------------ #33: imports build can use


def test_import_colmap_without_masks_fails_at_import(model_dir, tmp_path):
    """#33: "imported 12 images (0 masks)", exit 0, then build exited 4 on the first view."""
    sparse, images = _bin_model(tmp_path, model_dir)
    rgb = tmp_path / "rgb"
    rgb.mkdir()
    import cv2

    for p in images.iterdir():
        q = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(rgb / p.name), q[..., :3])  # RGB only: no matte anywhere
    case = Case(
        "colmap-no-masks",
        ("import", "colmap", "--model", str(sparse), "--images", str(rgb), "--out", "{T}/s"),
        2,
        r"has no matte: the image has no alpha channel and no mask was given; .*pass --masks DIR .*RGBA images",
        must_not_exist=("{T}/s",),
    )
    run_case(case, inputs={}, tmp_path=tmp_path / "run")


def test_colmap_export_keeps_alpha(model_dir, tmp_path):
    """#33: the COLMAP export wrote RGB over black; it must keep α so it re-imports."""
    _, images = _bin_model(tmp_path, model_dir)
    import cv2

    q = cv2.imread(str(sorted(images.iterdir())[0]), cv2.IMREAD_UNCHANGED)
    assert q.ndim == 3 and q.shape[2] == 4 and q[..., 3].min() < 128 < q[..., 3].max()


def test_colmap_binary_size_check_accepts_pycolmaps_files(model_dir, tmp_path):
    from opacityhull.colmapbin import check_colmap_binary

    sparse, _ = _bin_model(tmp_path, model_dir)
    check_colmap_binary(sparse)  # exactly the sizes the format gives
    p = sparse / "cameras.bin"
    p.write_bytes(p.read_bytes() + struct.pack("<d", 1.0))
    from opacityhull.errors import FormatError

    with pytest.raises(FormatError, match=r"8 unexpected byte\(s\) after the last record"):
        check_colmap_binary(sparse)


def test_colmap_export_import_build_round_trip_analytic(model_dir, tmp_path):
    """#33's round trip on the analytic model (fast; tests/e2e does it on the tiny plan)."""
    ex = tmp_path / "c"
    assert invoke(["export", model_dir, "--format", "colmap", "--out", ex]).exit_code == 0
    r = invoke(["import", "colmap", "--model", ex / "sparse" / "0", "--images", ex / "images", "--out", tmp_path / "s"])
    assert r.exit_code == 0 and "(12 masks)" in flat(r.stderr), r.output
    r = invoke(["build", tmp_path / "s", "--out", tmp_path / "m", "--no-pictures", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["surfels"] > 0


# ------------------------------------------------------------- build resume (item 5)


@pytest.mark.parametrize("name", ["cameras.pkl", "geometry.pkl"])
@pytest.mark.parametrize("content", ["text", "wrong-type"])
def test_resume_reruns_a_step_whose_cache_is_not_its_product(session_dir, tmp_path, name, content):
    """Item 5: a cache file overwritten with text or with a valid pickle of the wrong
    type was a ValueError traceback; the step must rerun (exit 0): the build's cache
    verification (``buildstore.cached``)."""
    import pickle

    m = tmp_path / "m"
    r = invoke(["build", session_dir, "--out", m, "--no-pictures"])
    assert r.exit_code == 0, r.output
    p = m / "build" / name
    if content == "text":
        p.write_text("(lp0\nI1\na.")  # pickle protocol 0 text: loads as a list
    else:
        p.write_bytes(pickle.dumps({"not": "the product"}))
    before = tree_digest(session_dir)
    r = invoke(["build", session_dir, "--out", m, "--no-pictures", "--resume", "--json"])
    assert r.exit_code == 0, r.output
    step = {"cameras.pkl": "cameras", "geometry.pkl": "geometry"}[name]
    assert json.loads(r.stdout)["steps"][step] == "ran"
    assert tree_digest(session_dir) == before


# ---------------------------------------------------------- SIGTERM, read-only disk


def test_sigterm_build_says_how_to_resume(session_dir, tmp_path):
    """A SIGTERM'd build exited 143 without a word; it says `build --resume` continues."""
    import signal
    import subprocess
    import sys
    import time

    before = tree_digest(session_dir)
    p = subprocess.Popen(
        [sys.executable, "-m", "opacityhull.cli", "build", str(session_dir), "--out", str(tmp_path / "m")],
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    )
    assert p.stderr is not None
    seen = []
    for line in p.stderr:  # on a pipe, build prints one line per finished step
        seen.append(line)
        if "build:" in line and "done in" in line:
            break
    time.sleep(0)  # the first step has finished: the build is working
    p.send_signal(signal.SIGTERM)
    rest = p.stderr.read()
    code = p.wait(timeout=120)
    if code == 0:
        pytest.skip("the build finished before the signal arrived")
    text = flat("".join(seen) + rest)
    assert code == 143, text
    assert "terminated by SIGTERM" in text and "`build --resume` continues" in text, text
    assert "Traceback" not in text
    assert tree_digest(session_dir) == before


def test_capture_onto_a_read_only_disk(tmp_path):
    """Item 13: exit 5 "not enough free disk space"; the README says exit 2, read-only."""
    import subprocess

    mnt = tmp_path / "ro"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m,ro", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()}); this test needs root")
    try:
        res = invoke(["capture", "--rig", "sim:builtin:diffuse", "--plan", "builtin:tiny", "--out", mnt / "s"])
        text = flat(res.stderr)
        assert res.exit_code == 2, res.output
        assert "read-only" in text and "free space" not in text and str(mnt / "s") in text, text
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# ------------------------------------------------------------------ rigs (item 12)

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "rig-emulated.toml"


def _emulate(tmp_path: Path, *faults: str):
    import subprocess
    import sys

    argv = [sys.executable, "-m", "opacityhull.cli", "rig", "emulate", "--config", str(EXAMPLE)]
    argv += ["--write-config", str(tmp_path / "rt.toml"), "--json"]
    for f in faults:
        argv += ["--fault", f]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    return proc, json.loads(proc.stdout.readline())


def test_vanish_at_start_does_not_hand_its_pty_to_another_device(tmp_path):
    """`--fault light_array:vanish:0`: the freed pty number went to the next emulator, so
    `rig check` talked to the wrong device (exit 2) instead of exit 3 naming light_array."""
    proc, info = _emulate(tmp_path, "light_array:vanish:0")
    try:
        urls = info["devices"]
        others = {u for n, u in urls.items() if not n.startswith("light_array")} | {urls["light_array.rotation"]}
        assert urls["light_array"] not in others  # distinct pty per emulator
        r = invoke(["rig", "check", "--config", tmp_path / "rt.toml", "--timeout", "0.3"])
        assert r.exit_code == 3, r.output
        assert re.search(r"rig check failed: light_array: .*cannot open", flat(r.stderr)), r.stderr
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_rig_check_after_a_safe_stop_is_not_busy(tmp_path):
    """After a capture's own safe stop (a completed feed hold, Hold:0), `rig check` called
    the board "busy (state Hold) — another program may be driving it"."""
    from opacityhull.rigs.config import load_rig_config
    from opacityhull.rigs.emulators.launch import start_emulators

    with start_emulators(load_rig_config(EXAMPLE), kind="pty") as emus:
        g = emus.by_device["turntable"]
        with g.lock:  # the state rig.safe()'s feed hold leaves once decelerated (tests/rigs drive it for real)
            g._state, g._sub = "Hold", 0
        emus.config.write(tmp_path / "rt.toml")
        r = invoke(["rig", "check", "--config", tmp_path / "rt.toml", "--timeout", "0.5", "--json"])
    text = flat(r.stderr)
    assert r.exit_code == 0, r.output
    assert "busy" not in text and "another program" not in text
    by = {d["name"]: d for d in json.loads(r.stdout)["devices"]}
    assert by["turntable"]["ok"] and "Hold:0" in by["turntable"]["detail"] and "safe stop" in by["turntable"]["detail"]
