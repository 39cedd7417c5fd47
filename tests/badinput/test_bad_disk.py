"""Full and read-only disks: every writer says so, names the path, exits 2, and leaves
what was already there intact (real tmpfs mounts; skipped where mounting is not allowed)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
from helpers import fill_with_zeros

from badkit import flat, invoke, tree_digest


def _mount(path: Path, size: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode().strip()}); these tests need root")


def _read_only(path: Path) -> None:
    r = subprocess.run(["mount", "-o", "remount,ro", str(path)], capture_output=True)
    assert r.returncode == 0, r.stderr


def _fill(path: Path) -> None:
    fill_with_zeros(path / "filler")
    with open(path / "filler", "ab", buffering=0) as f:  # the last partial block, byte by byte
        try:
            while True:
                f.write(b"\0")
        except OSError:
            pass
    # tmpfs may still hand out a page or an inode to a new file: take those too
    for i in range(1000):
        try:
            (path / f"filler{i}").write_bytes(b"\0" * 4096)
        except OSError:
            break


@pytest.fixture
def fs(tmp_path):
    mnt = tmp_path / "fs"
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _ro_with(fs: Path, src: Path | None = None, name: str = "in") -> Path | None:
    _mount(fs, "8m")
    dst = None
    if src is not None:
        dst = fs / name
        shutil.copytree(src, dst)
    (fs / "existing").mkdir()
    (fs / "existing" / "keep.txt").write_text("already written\n")
    _read_only(fs)
    return dst


def _check(r, *, what: str, path: str) -> None:
    text = flat(r.stderr)
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert what in text and path in text, text


def test_render_to_a_read_only_disk(fs, model_dir):
    _ro_with(fs)
    r = invoke(["render", model_dir, "--out", fs / "existing" / "x.png"])
    _check(r, what="read-only", path=str(fs / "existing" / "x.png"))
    assert (fs / "existing" / "keep.txt").read_text() == "already written\n"


def test_build_to_a_read_only_disk(fs, session_dir):
    _ro_with(fs)
    r = invoke(["build", session_dir, "--out", fs / "m", "--no-pictures"])
    _check(r, what="read-only", path=str(fs / "m"))


def test_relight_to_a_read_only_disk(fs, relight_model_dir):
    _ro_with(fs)
    r = invoke(["relight", relight_model_dir, "--out", fs / "relit", "--envmap", "builtin:grace", "--no-views"])
    _check(r, what="read-only", path=str(fs / "relit"))


def test_resume_on_a_read_only_disk_names_the_lock(fs, session_dir):
    from opacityhull.acquire.runner import _SessionLock
    from opacityhull.errors import WriteError

    s = _ro_with(fs, session_dir, "S")
    before = tree_digest(s)
    with pytest.raises(WriteError, match=r"cannot write .*S/\.capture\.lock: the file system is read-only"):
        _SessionLock(s).acquire()
    assert tree_digest(s) == before


def test_render_on_a_full_disk_says_full_not_opencv(fs, model_dir):
    _mount(fs, "256k")
    (fs / "earlier.png").write_bytes(b"an earlier result")
    _fill(fs)
    r = invoke(["render", model_dir, "--out", fs / "x.png"])
    _check(r, what="the disk is full", path=str(fs / "x.png"))
    assert "OpenCV could not write" not in flat(r.stderr)
    assert (fs / "earlier.png").read_bytes() == b"an earlier result"
    assert not [p.name for p in fs.iterdir() if p.name.startswith(".tmp")]  # no temporary left


def test_build_on_a_full_disk(fs, session_dir):
    _mount(fs, "256k")
    _fill(fs)
    r = invoke(["build", session_dir, "--out", fs / "m", "--no-pictures", "--hull-res", "24"])
    _check(r, what="the disk is full", path=str(fs / "m"))
    assert not (fs / "m" / "model.toml").exists()  # an unfinished build is marked by the missing model.toml
