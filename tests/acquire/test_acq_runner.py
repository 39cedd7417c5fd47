"""The capture runner on the laboratory rig: layout, resume, corruption, refusal,
disk full, device errors, and signals in a subprocess."""

from __future__ import annotations

import os
import random
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers import fill_with_zeros, python_child, with_pythonpath

from opacityhull.acquire.plan import parse_plan
from opacityhull.acquire.runner import DiskFull, device_pattern_id, resume_mismatch, run_capture
from opacityhull.acquire.schedule import expected_counts, schedule
from opacityhull.acquire.verify import verify_session
from opacityhull.errors import ConfigError, DeviceError, InputError
from opacityhull.session import Session, read_manifest

import rigkit
from rigkit import LabRig, tiny_plan

HERE = Path(__file__).parent


def expected():
    return expected_counts(schedule(tiny_plan(), LabRig().geometry))


@pytest.fixture
def rig():
    with LabRig() as r:
        yield r


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """One complete capture shared by the read-only tests."""
    out = tmp_path_factory.mktemp("cap") / "s"
    with LabRig() as r:
        res = run_capture(r, tiny_plan(), out, rig_source="lab")
    return out, res, r


def _manifest_ids(out):
    return [r.id for r in read_manifest(Path(out) / "manifest.jsonl")]


def test_complete_capture_layout(captured):
    out, res, r = captured
    want = expected()
    assert res.complete and res.images == sum(want.values()) == res.taken
    assert res.per_phase == want
    rep = verify_session(out)
    assert rep["ok"] and rep["complete"] and rep["per_phase"] == want
    assert rep["missing"] == rep["corrupt"] == rep["unlisted"] == []
    ids = _manifest_ids(out)
    assert len(ids) == len(set(ids)) == sum(want.values())
    # operator steps in order; ground truth for exactly the object views
    assert r.operator_log == ["place_board", "remove_board", "remove_object", "place_object"]
    assert sorted(map(tuple, r.ground_truth_calls[0])) == sorted((c, a) for c in range(3) for a in (0, 90, 180, 270))
    _assert_safe(r)  # read from the emulators
    sess = Session.open(out)
    assert sess.white_level == 1.0
    assert sess.charuco.squares_x == 5
    assert sess.source == "lab"
    assert len(sess.views("lightfield")) == 12
    assert sess.is_simulated  # the lab rig writes groundtruth/


def test_patterns_saved_exactly_as_uploaded(captured):
    out, _, r = captured
    sess = Session.open(out)
    pats = sess.patterns
    assert sorted(pats) == ["p001", "p002", "p003", "p004"]
    assert pats["p002"]["kind"] == "complement" and pats["p002"]["of"] == 1
    for key, entry in pats.items():
        pid = entry["id"]
        for di, disp in enumerate(("bottom", "back")):
            stored = r.display_emulator.pattern(device_pattern_id(pid, di))
            saved = np.round(sess.pattern_image(disp, pid) * 255).astype(np.uint8)
            assert np.array_equal(stored, saved), (key, disp)
    p1 = np.round(sess.pattern_image("bottom", 1) * 255).astype(int)
    p2 = np.round(sess.pattern_image("bottom", 2) * 255).astype(int)
    assert np.array_equal(p1 + p2, np.full_like(p1, 255))
    assert np.abs(p1 - p2).min() >= 129


def test_images_show_the_rig_state(captured):
    out, _, r = captured
    sess = Session.open(out)
    # object-absent matting image = the bottom pattern as the camera sees it, times exposure
    rec = sess.select(phase="matting", camera=0, table_deg=90.0, pattern=3, object_present=False)[0]
    img = sess.load_image(rec)
    pat = np.round(sess.pattern_image("bottom", 3) * 255).astype(np.uint8)
    from opacityhull.rigs.display_protocol import nearest_resize

    want = nearest_resize(pat, 24, 18).astype(np.float32) / 255 * rec.exposure_s
    np.testing.assert_allclose(img, want, atol=1e-6)
    # reflectance: one light on -> radiance proportional to one light; brackets agree once divided by t
    recs = sorted(
        sess.select(phase="reflectance", camera=1, table_deg=0.0, light=0, lights_deg=0.0), key=lambda q: q.exposure_s
    )
    assert [q.exposure_s for q in recs] == [0.25, 1.0]
    a, b = (sess.load_image(q) / q.exposure_s for q in recs[:2])
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    rad = sess.load_radiance(recs[0].shot)
    np.testing.assert_allclose(rad, a, rtol=1e-5, atol=1e-6)


def test_second_capture_into_non_empty_dir_is_refused(captured, rig, tmp_path):
    out, _, _ = captured
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    with pytest.raises(InputError, match="not empty.*--resume"):
        run_capture(rig, tiny_plan(), out)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before
    other = tmp_path / "x"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        run_capture(rig, tiny_plan(), other)
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    # --resume into a folder that holds something else than a session is refused too
    with pytest.raises(InputError, match="no session.toml"):
        run_capture(rig, tiny_plan(), other, resume=True)


def test_corrupt_images_are_reported_and_reshot(rig, tmp_path):
    out = tmp_path / "s"
    run_capture(rig, tiny_plan(), out)
    sess = Session.open(out)
    victims = [sess.select(phase="matting")[7], sess.select(phase="reflectance")[3], sess.select(phase="lightfield")[0]]
    p0, p1, p2 = (out / v.path for v in victims)
    p0.write_bytes(p0.read_bytes()[: p0.stat().st_size // 2])  # truncated
    data = bytearray(p1.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte, same size
    p1.write_bytes(bytes(data))
    p2.unlink()  # missing
    rep = verify_session(out)
    assert not rep["ok"]
    assert sorted(rep["corrupt"]) == sorted([victims[0].path, victims[1].path])
    assert rep["missing"] == [victims[2].path]
    res = run_capture(rig, tiny_plan(), out, resume=True)
    assert res.complete and res.taken == 3 and res.reshot == 3
    rep = verify_session(out)
    assert rep["ok"] and rep["complete"] and rep["superseded"] == 3
    assert rep["per_phase"] == expected()
    ids = _manifest_ids(out)
    assert len(ids) == sum(expected().values()) + 3 and len(set(ids)) == sum(expected().values())
    # the re-shot images are identical to the originals (the rig state is reproduced exactly)
    sess2 = Session.open(out)
    for v in victims:
        new = [r for r in sess2.records if r.id == v.id][0]
        assert new.sha256 == v.sha256


def test_resume_of_complete_session_takes_nothing_and_plan_must_match(captured, rig):
    out, _, _ = captured
    n_lines = len(_manifest_ids(out))
    res = run_capture(rig, tiny_plan(), out, resume=True)
    assert res.complete and res.taken == 0
    assert len(_manifest_ids(out)) == n_lines
    other = dict(rigkit.TINY_PLAN, plan={"name": "lab-tiny", "seed": 6})
    with pytest.raises(ConfigError, match=r"differs from the plan.*plan\.seed: 5 in the session, 6 now"):
        run_capture(rig, parse_plan(other, where="other"), out, resume=True)
    assert resume_mismatch(out, tiny_plan(), rig.geometry) is None
    assert "plan.seed" in resume_mismatch(out, parse_plan(other, where="other"), rig.geometry)
    assert resume_mismatch(out.parent / "no-session-here", tiny_plan(), rig.geometry) is None


def _assert_safe(rig):
    rig.settle()  # DMX is not acknowledged: the all-off packet may still be in the pty
    assert not rig.display_emulator.is_lit()
    assert all(v == 0 for v in rig.dmx_levels().values())
    assert not rig.grbl.is_moving
    assert b"!" in rig.grbl.received  # the feed hold was sent


def _on_capture(rig, n_at, fn):
    n = {"k": 0}

    def hook(cam):
        n["k"] += 1
        if n["k"] == n_at:
            fn()

    for c in rig.cameras:
        c.before_capture = hook


def test_device_error_leaves_rig_safe_and_session_resumable(tmp_path):
    out = tmp_path / "s"
    with LabRig() as rig:
        _on_capture(rig, 50, lambda: rig.grbl.inject_alarm(1))  # hard limit mid-matting
        with pytest.raises(DeviceError, match="(?i)alarm.*--resume"):
            run_capture(rig, tiny_plan(), out)
        _assert_safe(rig)
    n1 = len(_manifest_ids(out))
    assert 0 < n1 < sum(expected().values())
    assert verify_session(out)["ok"]
    with LabRig() as rig:  # the controller was reset and homed by the operator
        res = run_capture(rig, tiny_plan(), out, resume=True)
        # resuming in the matting object stage re-issued its manual steps
        assert rig.operator_log == ["remove_board", "place_object"]
    assert res.complete and res.taken == sum(expected().values()) - n1
    rep = verify_session(out)
    assert rep["ok"] and rep["per_phase"] == expected() and rep["superseded"] == 0


def test_display_vanishes_mid_run(tmp_path):
    out = tmp_path / "s"
    with LabRig() as rig:
        _on_capture(rig, 40, rig.display_server.vanish)
        with (
            pytest.raises(DeviceError, match="--resume"),
            pytest.warns(RuntimeWarning, match="clean-up incomplete: backdrops"),
        ):
            run_capture(rig, tiny_plan(), out)
        rig.settle()
        assert all(v == 0 for v in rig.dmx_levels().values())
        assert not rig.grbl.is_moving and b"!" in rig.grbl.received
    assert verify_session(out)["ok"]
    with LabRig() as rig2:  # "plugged back in": a fresh controller that lost its patterns
        res = run_capture(rig2, tiny_plan(), out, resume=True)
        assert len(rig2.display_emulator.stored_ids()) == 8  # 4 patterns x 2 displays uploaded again
    assert res.complete
    rep = verify_session(out)
    assert rep["ok"] and rep["per_phase"] == expected()


def _tmpfs(path: Path, size: str):
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()}); disk-full tests need root")


@pytest.fixture
def small_fs(tmp_path):
    mnt = tmp_path / "fs"
    yield mnt
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_disk_check_before_start(rig, small_fs):
    _tmpfs(small_fs, "64k")
    with pytest.raises(DiskFull, match=r"needs about [\d.]+ MB .* [\d.]+ MB are free"):
        run_capture(rig, tiny_plan(), small_fs / "s")
    assert not (small_fs / "s").exists()


def test_disk_fills_up_mid_run(rig, small_fs):
    """A real ENOSPC: a 4 MB tmpfs passes the start check, then another writer fills it."""
    _tmpfs(small_fs, "4m")
    out = small_fs / "s"
    n = {"k": 0}

    def fill(cam):
        n["k"] += 1
        if n["k"] == 60:
            fill_with_zeros(small_fs / "filler")

    for c in rig.cameras:
        c.before_capture = fill
    with pytest.raises(DiskFull, match="disk full.*--resume"):
        run_capture(rig, tiny_plan(), out)
    _assert_safe(rig)
    n_listed = len(_manifest_ids(out))
    assert 0 < n_listed < sum(expected().values())
    rep = verify_session(out)
    assert rep["ok"], rep  # nothing half-written is listed, no stray temporaries
    (small_fs / "filler").unlink()
    for c in rig.cameras:
        c.before_capture = None
    res = run_capture(rig, tiny_plan(), out, resume=True)
    assert res.complete
    rep = verify_session(out)
    assert rep["ok"] and rep["per_phase"] == expected()
    ids = _manifest_ids(out)
    assert len(ids) == len(set(ids))


def _child(out: Path, *args):
    return python_child(HERE / "rigkit.py", str(out), *args, env=with_pythonpath(HERE))


def _run_until(proc, n_images: int, sig) -> None:
    for line in proc.stdout:
        if line.startswith("img ") and int(line.split()[1]) >= n_images:
            proc.send_signal(sig)
            break


@pytest.mark.parametrize("sig, seed", [(signal.SIGKILL, 1), (signal.SIGKILL, 2), (signal.SIGINT, 3)])
def test_signal_at_random_point_then_resume(tmp_path, sig, seed):
    total = sum(expected().values())
    k = random.Random(seed).randrange(3, total - 3)
    out = tmp_path / "s"
    proc = _child(out)
    _run_until(proc, k, sig)
    rest, err = proc.communicate(timeout=60)
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL
    else:
        assert proc.returncode == 130, err
        # the child reports the rig state after rig.safe() ran
        rigkit.assert_left_safe([x for x in rest.splitlines() if x.startswith("interrupted")][0])
    listed = len(_manifest_ids(out))
    assert k <= listed < total
    rigkit.assert_resumed_to_the_end(_child(out, "--resume"), out, listed=listed, total=total, timeout_s=60)
    rep = verify_session(out)
    assert rep["ok"], rep
    assert rep["per_phase"] == expected() and rep["superseded"] == 0


def test_concurrent_capture_into_one_session_is_refused(captured, rig):
    from opacityhull.acquire.runner import _SessionLock

    out, _, _ = captured
    other = _SessionLock(out)
    other.acquire()  # another capture holds the session
    try:
        with pytest.raises(InputError, match=f"another capture is writing this session \\(process {os.getpid()}"):
            run_capture(rig, tiny_plan(), out, resume=True)
    finally:
        other.release()
    assert not (out / ".capture.lock").exists()
    assert run_capture(rig, tiny_plan(), out, resume=True).complete  # free again


def test_ctrl_c_wrapped_by_a_library_is_still_ctrl_c(tmp_path):
    """Dr.Jit turns a KeyboardInterrupt inside mi.render into a RuntimeError caused by it."""
    out = tmp_path / "s"

    def wrapped():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("drjit.custom(...): error while performing a custom operation") from e

    with LabRig() as rig:
        _on_capture(rig, 30, wrapped)
        with pytest.raises(KeyboardInterrupt):
            run_capture(rig, tiny_plan(), out)
        _assert_safe(rig)
    assert verify_session(out)["ok"] and 0 < len(_manifest_ids(out)) < sum(expected().values())


def test_ground_truth_failure_is_reported_and_retried_on_resume(tmp_path):
    from opacityhull.acquire.runner import GroundTruthError

    out = tmp_path / "s"
    with LabRig() as rig:
        real = rig.ground_truth
        rig.ground_truth = lambda root, views: (_ for _ in ()).throw(ImportError("simulator half-installed"))
        with pytest.raises(GroundTruthError, match="all 222 images are captured.*ImportError.*--resume"):
            run_capture(rig, tiny_plan(), out)
        assert verify_session(out)["complete"]
        rig.ground_truth = real
        res = run_capture(rig, tiny_plan(), out, resume=True)
        assert res.complete and res.taken == 0 and len(rig.ground_truth_calls) == 1
    assert (out / "groundtruth" / "views.json").is_file()
