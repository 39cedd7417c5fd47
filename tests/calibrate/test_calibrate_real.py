"""``opacityhull calibrate`` on real photographs made by others (vendored in
tests/data/real/calibration/, see the SOURCE.txt files), against the other tools' own
estimates.

Thresholds from measured spread:

- OpenCV photographs. OpenCV's reference (reference_camera.yml, 2021) came from its
  ``calibrate_camera_charuco`` sample: markers decoded, a first calibration from the marker
  corners (``calibrateCameraAruco``), the ChArUco corners interpolated through that camera,
  then ``calibrateCameraCharuco``, flags 0. ``calibrate``'s default ``--interpolate
  aruco-calib`` is that pipeline: fx/fy/cx/cy +0.63/+0.77/-0.08/+0.28 % of the reference and
  RMS 0.1828 px against its 0.1823 (the RMS agreeing to 0.3 % says it is the same corners).
  Asserted: within 1 % (the goal) and 1 sigma, RMS within 0.005 px of the reference's.
  Why not tighter: the four photographs pin fx to +-15.9 px (3.5 %, sigma from the
  Jacobian, equal to OpenCV's ``stdDeviationsIntrinsics``), and ``cornerSubPix`` stops at
  0.1 px (OpenCV's ``cornerRefinementMinAccuracy``), so where a corner's refinement starts
  moves fx: the one-pass ``homography`` interpolation gives +1.06 %, a second pass through
  our own calibration +1.05 to +1.17 %, through it with fx scaled by 0.97/1.03 +1.73/+0.67 %;
  refining to convergence with a fixed window of 3..10 px gives fx 421.9-473.1 px
  (benchmarks/calibration_real.py). A 1 % goal on these four photographs is met, and is
  within their noise.
- caliscope's webcams. The focal and centre goals are met on every frame of the extrinsic
  videos (vendored as corners); the 1 deg rotation goal only with caliscope's intrinsics
  held. With ours, the rotations differ as the principal points do, and a hold-out shows the
  videos cannot tell the two sets of intrinsics apart (each frame's pose absorbs the
  principal point). Trusted where they differ: caliscope's principal points (its own
  intrinsic recordings, 33-40 boards, are not in its repository; ours rest on 27-45 frames
  with sigma 4-16 px) and our poses given them; the focal lengths agree within our sigma.
  The intrinsic/ videos are another session (prerecorded_calibration, with its own
  caliscope estimate): not comparable with camera_array.toml (benchmarks/calibration_real.py).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from helpers import invoke_cli

DATA = Path(__file__).resolve().parents[1] / "data" / "real" / "calibration"
OPENCV = DATA / "opencv"
CALISCOPE = DATA / "caliscope"
BOARD = "squares=5x7,square_m=0.04,marker_m=0.02,dictionary=DICT_6X6_250"
REF = {"fx": 452.51072219637672, "fy": 456.76707935146891, "cx": 317.70297317353277, "cy": 277.75155919135995}
REF_RMS_PX = 0.18234905535936044


@pytest.fixture(scope="module")
def opencv_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ocv") / "calib"
    imgs = sorted(OPENCV.glob("img_0*.jpg"))
    r = invoke_cli(["calibrate", *imgs, "--board", BOARD, "--out", out, "--json"])
    assert r.exit_code == 0, r.stderr
    return json.loads(r.stdout), out


def test_opencv_photos_match_opencvs_own_calibration(opencv_run):
    s, _ = opencv_run
    (cam,) = s["cameras"]
    assert cam["rms_px"] <= 0.25
    assert abs(cam["rms_px"] - REF_RMS_PX) <= 0.005, cam["rms_px"]  # measured 0.1828
    for k, ref in REF.items():
        assert abs(cam[k] - ref) <= cam["std"][k], (k, cam[k], ref, cam["std"][k])
        assert abs(cam[k] / ref - 1) <= 0.01, (k, cam[k], ref)  # measured +0.63/+0.77/-0.08/+0.28 %
    assert s["rejected"] == [] and s["left_out"] == []


def test_opencv_default_is_opencvs_sample_pipeline(opencv_run):
    """The default equals OpenCV's ``calibrate_camera_charuco`` sample written out with
    OpenCV alone (markers, ``calibrateCamera`` on their corners, the ChArUco corners
    interpolated through that camera, ``calibrateCamera`` on them, flags 0), at one
    OpenCV thread as ``calibrate`` solves: with OpenCV's threads the first calibration
    differs in its 12th digit from run to run, and the corners interpolated through it
    (cornerSubPix stops at 0.1 px) move fx by up to 1.4e-3 px (3e-6)."""

    from opacityhull.charuco import single_threaded_solvers

    with single_threaded_solvers():
        _opencv_sample_pipeline_matches(opencv_run)


def _opencv_sample_pipeline_matches(opencv_run):
    import cv2

    s, _ = opencv_run
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250)
    board = cv2.aruco.CharucoBoard((5, 7), 0.04, 0.02, d)
    grays = [np.asarray(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in sorted(OPENCV.glob("img_0*.jpg"))]
    markers = [cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters()).detectMarkers(g)[:2] for g in grays]
    obj_of = {int(i): p for i, p in zip(np.ravel(board.getIds()), board.getObjPoints(), strict=True)}
    mo = [np.concatenate([obj_of[int(i)] for i in ids.ravel()]).astype(np.float32) for _, ids in markers]
    mi = [np.concatenate([c.reshape(-1, 2) for c in corners]).astype(np.float32) for corners, _ in markers]
    _, K0, d0, _, _ = cv2.calibrateCamera(mo, mi, (640, 480), None, None)  # pyright: ignore[reportCallIssue, reportArgumentType]
    params = cv2.aruco.CharucoParameters()
    params.cameraMatrix, params.distCoeffs = K0, d0
    det = cv2.aruco.CharucoDetector(board, params, cv2.aruco.DetectorParameters())
    objs, imgs = [], []
    for g, (corners, ids) in zip(grays, markers, strict=True):
        cc, ci, _, _ = det.detectBoard(g, markerCorners=corners, markerIds=ids)
        o, i = board.matchImagePoints(cc, ci)  # pyright: ignore[reportCallIssue, reportArgumentType]
        objs.append(o.astype(np.float32))
        imgs.append(i.astype(np.float32))
    rms, K, _, _, _ = cv2.calibrateCamera(objs, imgs, (640, 480), None, None)  # pyright: ignore[reportCallIssue, reportArgumentType]
    cam = s["cameras"][0]
    np.testing.assert_allclose([cam["fx"], cam["fy"], cam["cx"], cam["cy"]], K[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=1e-6)
    assert abs(cam["rms_px"] - rms) <= 1e-6


def test_opencv_photos_one_pass_interpolation():
    """``--interpolate homography`` (one decoding pass, OpenCV's ``CharucoDetector`` alone):
    within 1 sigma and 1.1 % (measured +1.06/+1.00/-0.15/-0.77 %, RMS 0.1878 px), a worse
    RMS than the default's on the same photographs."""
    imgs = sorted(OPENCV.glob("img_0*.jpg"))
    r = invoke_cli(["calibrate", *imgs, "--board", BOARD, "--json", "--interpolate", "homography"])
    assert r.exit_code == 0, r.stderr
    (cam,) = json.loads(r.stdout)["cameras"]
    assert REF_RMS_PX + 0.003 <= cam["rms_px"] <= 0.25
    for k, ref in REF.items():
        assert abs(cam[k] - ref) <= cam["std"][k], (k, cam[k], ref, cam["std"][k])
        assert abs(cam[k] / ref - 1) <= 0.011, (k, cam[k], ref)


def test_opencv_std_matches_opencvs_jacobian(opencv_run):
    """The per-parameter σ against OpenCV's own ``stdDeviationsIntrinsics`` on the same corners."""
    import cv2

    from opacityhull.calibrate.inputs import camera_inputs, detect_frames, parse_board, reinterpolate_frames

    s, _ = opencv_run
    spec = parse_board(BOARD)
    (cam_in,) = camera_inputs(sorted(OPENCV.glob("img_0*.jpg")))
    dc = reinterpolate_frames(detect_frames(cam_in, charuco=spec), charuco=spec)
    objs = [o.detection.object_points.astype(np.float32) for o in dc.observations]
    imgs = [o.detection.image_points.astype(np.float32) for o in dc.observations]
    out = cv2.calibrateCameraExtended(objs, imgs, (640, 480), np.eye(3), np.zeros(5))
    K, sd = out[1], np.asarray(out[5]).ravel()
    cam = s["cameras"][0]
    np.testing.assert_allclose([cam["fx"], cam["fy"], cam["cx"], cam["cy"]], K[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=1e-6)
    np.testing.assert_allclose([cam["std"][k] for k in ("fx", "fy", "cx", "cy")], sd[:4], rtol=0.01)


def test_opencv_outputs_read_back(opencv_run):
    import cv2
    import pycolmap

    s, out = opencv_run
    cam = s["cameras"][0]
    fs = cv2.FileStorage(str(out / "cam0.yaml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    np.testing.assert_allclose(K[[0, 1, 0, 1], [0, 1, 2, 2]], [cam["fx"], cam["fy"], cam["cx"], cam["cy"]], rtol=1e-12)
    np.testing.assert_allclose(dist, cam["dist"], rtol=1e-12)
    rec = pycolmap.Reconstruction(str(out / "colmap"))
    (c,) = rec.cameras.values()
    # COLMAP's pixel convention puts the top-left pixel's centre at (0.5, 0.5)
    np.testing.assert_allclose(c.params[:4], [cam["fx"], cam["fy"], cam["cx"] + 0.5, cam["cy"] + 0.5], rtol=1e-9)
    for png in ("reprojection_histogram.png", "per_frame_rms.png"):
        assert (out / png).stat().st_size > 5000
    assert json.loads((out / "rejected.json").read_text()) == []


def _caliscope_ref():
    """caliscope's camera_array.toml: K, dist and cam_from_world rotation by camera, (4, 3) centres."""
    from opacityhull.calibrate.caliscope import read_camera_array

    cams = read_camera_array(CALISCOPE / "camera_array.toml")
    K = {i: c.K for i, c in cams.items()}
    D = {i: c.dist for i, c in cams.items()}
    return K, D, {i: c.R_cam_from_world for i, c in cams.items()}, np.array([c.centre_world for c in cams.values()])


def _video_corners():
    """The corners ``calibrate`` found in every frame of caliscope's four extrinsic videos
    (extrinsic_corners.npz, written by benchmarks/calibration_real.py --write-corners; see
    SOURCE.txt), as the detections ``calibrate_detected`` takes."""
    from opacityhull.calibrate.corners import read_corners
    from opacityhull.calibrate.inputs import parse_board

    spec = parse_board(str(CALISCOPE / "charuco.toml"))
    sources = [f"cam_{i}.mp4" for i in range(4)]
    return spec, read_corners(CALISCOPE / "extrinsic_corners.npz", charuco=spec, size=(1280, 720), sources=sources)


def _calibrate_video_corners(intrinsics=()):
    from opacityhull.calibrate.run import CalibrateOptions, calibrate_detected

    spec, dets = _video_corners()
    opts = CalibrateOptions(intrinsics=intrinsics)
    return calibrate_detected(dets, charuco=spec, options=opts, cameras=[d.camera for d in dets])


def _poses_vs_caliscope(cams) -> tuple[np.ndarray, dict[tuple[int, int], float]]:
    _, _, Rr, C_ref = _caliscope_ref()
    C = np.array([-cams[i].cam_from_world[:3, :3].T @ cams[i].cam_from_world[:3, 3] for i in range(4)])
    rot = {}
    for i in range(4):
        for j in range(i + 1, 4):
            Ro = cams[j].cam_from_world[:3, :3] @ cams[i].cam_from_world[:3, :3].T
            rot[(i, j)] = _rotation_deg(Ro.T @ (Rr[j] @ Rr[i].T))
    return _similarity_residuals(C, C_ref), rot


def test_caliscope_full_videos_intrinsics_and_centres():
    """Every frame of caliscope's four extrinsic videos (their corners, vendored), each
    camera calibrated from all the frames it sees the board in (the out-of-sync ones too:
    44/27/43/45 frames), against caliscope's camera_array.toml:

    - focal length (fx + fy) / 2 within 2 % (the goal; measured +0.4/+1.1/-0.2/-0.3 %, each
      within 1 sigma of our Jacobian's 0.4/1.1/1.3/2.3 %), fx within 2 % (+1.2/+0.1/-0.5/-0.1);
      each camera's own RMS <= 0.6 px (0.09-0.20);
    - the centres within 2 cm after a similarity alignment (0.40-0.59 cm).

    The relative rotations (1.7-4.5 deg) are not within the 1 deg goal. They differ from
    caliscope's as the two principal points do (ours 3-33 px from caliscope's, sigma 4-16 px):
    each pair within 3 sigma of the rotation those sigmas imply (measured at most 2.75).
    With the out-of-sync frames left out (before), cam 2's focal was -4.3 %."""
    run = _calibrate_video_corners()
    cams = run.result.cameras
    Kc, _, _, _ = _caliscope_ref()
    for i in range(4):
        f = cams[i]
        focal, ref = (f.K[0, 0] + f.K[1, 1]) / 2, (Kc[i][0, 0] + Kc[i][1, 1]) / 2
        assert abs(focal / ref - 1) <= 0.02, (i, focal, ref)
        assert abs(f.K[0, 0] / Kc[i][0, 0] - 1) <= 0.02, (i, f.K[0, 0])
        assert f.intrinsic_rms_px <= 0.6
    assert [cams[i].intrinsic_frames for i in range(4)] == [44, 27, 43, 45]
    assert [sum(1 for n in run.notes if n.startswith(f"camera {i}: ") and "out of sync" in n) for i in range(4)] == [
        1
    ] * 4
    centres, rot = _poses_vs_caliscope(cams)
    assert centres.max() <= 0.02, centres
    sig = {i: math.degrees(math.hypot(cams[i].std["cx"], cams[i].std["cy"]) / cams[i].K[0, 0]) for i in range(4)}
    for (i, j), e in rot.items():
        assert e <= 3.0 * math.hypot(sig[i], sig[j]), (i, j, e, sig[i], sig[j])


def test_caliscope_full_videos_poses_with_its_intrinsics():
    """The same corners with caliscope's intrinsics held: the six relative rotations within
    1 deg (the goal; measured 0.34-0.79) and the centres within 2 cm (0.32-0.61 cm)."""
    Kc, Dc, _, _ = _caliscope_ref()
    held = tuple((i, Kc[i], Dc[i], (1280, 720), "camera_array.toml") for i in range(4))
    run = _calibrate_video_corners(held)
    centres, rot = _poses_vs_caliscope(run.result.cameras)
    assert centres.max() <= 0.02, centres
    assert max(rot.values()) <= 1.0, rot


def test_caliscope_videos_cannot_tell_the_two_intrinsics_apart():
    """Four-fold hold-out on each camera's frames: intrinsics fitted on 3/4, the other
    quarter's per-frame PnP residual through them and through caliscope's. Ours are never
    worse by more than 0.005 px (measured: better by up to 0.023 px on cam 0, within 0.002 px
    elsewhere), though the two principal points are up to 33 px apart: a frame's own pose
    absorbs the principal point, which is why the relative rotations rest on it."""
    import cv2

    from opacityhull.calibrate.inputs import screen_frames

    Kc, Dc, _, _ = _caliscope_ref()
    spec, dets = _video_corners()

    def rms(obs, K, dist):
        e = []
        for o in obs:
            _, rv, tv = cv2.solvePnP(o.detection.object_points, o.detection.image_points, K, dist)
            uv, _ = cv2.projectPoints(o.detection.object_points, rv, tv, K, dist)
            e.append(np.sum((uv.reshape(-1, 2) - o.detection.image_points) ** 2, axis=1))
        return float(np.sqrt(np.mean(np.concatenate(e))))

    for i, d in enumerate(dets):
        obs = screen_frames(d, charuco=spec).observations
        for fold in range(4):
            train = [o for k, o in enumerate(obs) if k % 4 != fold]
            test = [o for k, o in enumerate(obs) if k % 4 == fold]
            _, K, dist, _, _ = cv2.calibrateCamera(  # pyright: ignore[reportCallIssue]
                [o.detection.object_points.astype(np.float32) for o in train],
                [o.detection.image_points.astype(np.float32) for o in train],
                (1280, 720),
                None,  # pyright: ignore[reportArgumentType]
                None,  # pyright: ignore[reportArgumentType]
            )
            assert rms(test, K, dist) <= rms(test, Kc[i], Dc[i]) + 0.005, (i, fold)


def test_caliscope_inverted_board_four_cameras(tmp_path):
    """The vendored frames of caliscope's four webcams (inverted print, found by trying both
    polarities), every camera calibrated from them alone: each camera's own RMS <= 0.6 px
    (measured 0.14-0.23) and the centres within 2 cm of caliscope's after a similarity
    alignment (measured 0.49-1.45 cm). The focal lengths (+1.4/-2.4/-6.5/+0.9 % on fx) and
    relative rotations (1.6-8.7 deg) are NOT asserted here: these 9-14 frames of a 12-corner
    board pin fx to 7-30 px (1-5 %) and the principal point to 7-39 px. The goals are
    asserted on every frame of the videos (test_caliscope_full_videos_*)."""
    import tomllib

    r = invoke_cli(
        ["calibrate", *(CALISCOPE / f"cam_{i}" for i in range(4)), "--board", CALISCOPE / "charuco.toml", "--json"]
    )
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    ref = tomllib.loads((CALISCOPE / "camera_array.toml").read_text())["cameras"]
    cams = {c["index"]: c for c in s["cameras"]}
    assert sorted(cams) == [0, 1, 2, 3]
    for c in cams.values():
        assert c["intrinsic_rms_px"] <= 0.6
    C_ref = []
    C_our = []
    for i in range(4):
        R = np.array(ref[str(i)]["rotation"])
        C_ref.append(-R.T @ np.array(ref[str(i)]["translation"]))
        C_our.append(np.array(cams[i]["centre_m"]))
    C_ref, C_our = np.array(C_ref), np.array(C_our)
    err = _similarity_residuals(C_our, C_ref)
    assert err.max() <= 0.02, err
    del tmp_path


def _rotation_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def test_caliscope_poses_with_its_intrinsics(tmp_path):
    """The same frames with caliscope's intrinsics held (``--intrinsics``, one OpenCV YAML
    per camera): the four centres within 2 cm of caliscope's after a similarity alignment
    (measured 0.25–0.47 cm) and the six relative rotations within 1° (measured 0.19–0.54°,
    1–2 σ of our Jacobian's 0.14–0.26°). The ~1 px joint RMS is in the data: frames of one
    instant are exposed up to 5 ms apart while the board moves by hand (held intrinsics or
    ours, the joint RMS is the same)."""
    import tomllib

    from opacityhull.camera import Camera, write_opencv_yaml

    ref = tomllib.loads((CALISCOPE / "camera_array.toml").read_text())["cameras"]
    args = []
    for i in range(4):
        p = tmp_path / f"cam{i}.yaml"
        K, dist = np.array(ref[str(i)]["matrix"]), np.array(ref[str(i)]["distortions"])
        write_opencv_yaml(p, Camera(K=K, dist=dist, width=1280, height=720))
        args += ["--intrinsics", p]
    r = invoke_cli(
        [
            "calibrate",
            *(CALISCOPE / f"cam_{i}" for i in range(4)),
            "--board",
            CALISCOPE / "charuco.toml",
            "--json",
            *args,
        ]
    )
    assert r.exit_code == 0, r.stderr
    cams = {c["index"]: c for c in json.loads(r.stdout)["cameras"]}
    Rr = {i: np.array(ref[str(i)]["rotation"]) for i in range(4)}
    C_ref = np.array([-Rr[i].T @ np.array(ref[str(i)]["translation"]) for i in range(4)])
    C_our = np.array([cams[i]["centre_m"] for i in range(4)])
    assert _similarity_residuals(C_our, C_ref).max() <= 0.02
    for i in range(4):
        for j in range(i + 1, 4):
            Ro = np.array(cams[j]["cam_from_world"])[:3, :3] @ np.array(cams[i]["cam_from_world"])[:3, :3].T
            assert _rotation_deg(Ro.T @ (Rr[j] @ Rr[i].T)) <= 1.0, (i, j)
    assert cams[0]["held"] == ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]


def _similarity_residuals(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distances after the least-squares similarity (Umeyama) src → dst."""
    ms, md = src.mean(0), dst.mean(0)
    A = (dst - md).T @ (src - ms) / len(src)
    U, S, Vt = np.linalg.svd(A)
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = np.trace(np.diag(S) @ E) / np.mean(np.sum((src - ms) ** 2, axis=1))
    return np.linalg.norm((s * (R @ (src - ms).T)).T + md - dst, axis=1)


# ---- bad input


def test_board_matching_no_print_names_polarity(tmp_path):
    imgs = sorted(OPENCV.glob("img_0*.jpg"))
    r = invoke_cli(["calibrate", *imgs, "--board", "squares=5x7,square_m=0.04,marker_m=0.02,dictionary=DICT_4X4_50"])
    assert r.exit_code == 2
    assert "both print polarities" in r.stderr and "DICT_4X4_50" in r.stderr


def test_inverted_board_with_normal_polarity_says_try_inverted():
    board = "squares=4x5,square_m=0.054,marker_m=0.0405,dictionary=DICT_4X4_1000,polarity=normal"
    r = invoke_cli(["calibrate", CALISCOPE / "cam_0", "--board", board])
    assert r.exit_code == 2
    assert "try polarity=inverted" in r.stderr


def test_undecodable_video_exit_4(tmp_path):
    bad = tmp_path / "cam.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    r = invoke_cli(["calibrate", bad, "--board", BOARD])
    assert r.exit_code == 4, r.output
    assert "cam.mp4" in r.stderr


def test_images_of_different_sizes_exit_2(tmp_path):
    import cv2

    imgs = sorted(OPENCV.glob("img_0*.jpg"))
    for p in imgs[:3]:
        shutil.copy(p, tmp_path / p.name)
    g = cv2.imread(str(imgs[3]))
    assert g is not None
    cv2.imwrite(str(tmp_path / "img_03.jpg"), cv2.resize(g, (320, 240)))
    r = invoke_cli(["calibrate", *sorted(tmp_path.glob("*.jpg")), "--board", BOARD])
    assert r.exit_code == 2
    assert "img_03.jpg" in r.stderr and "320x240" in r.stderr


def test_fewer_frames_than_parameters_exit_2():
    imgs = sorted(OPENCV.glob("img_0*.jpg"))[:2]
    r = invoke_cli(["calibrate", *imgs, "--board", BOARD])
    assert r.exit_code == 2
    assert "fewer frames than the parameters need" in r.stderr


def test_bad_board_flag_exit_2():
    r = invoke_cli(["calibrate", OPENCV / "img_00.jpg", "--board", "squares=5by7,square_m=0.04"])
    assert r.exit_code == 2 and "--board" in r.stderr


def test_video_frames_rejection_report(tmp_path):
    """A video made of the OpenCV photographs with a repeated frame, a blurred one and a
    blank one: the kept frames calibrate, the others are listed with their reason. The
    blur (Gaussian σ 0.8 px) keeps all 24 corners detectable but leaves 10 % of the
    Laplacian variance (the four photographs lie within 0.6–1.0 × their median: 4814–8006)."""
    import cv2

    imgs = [np.asarray(cv2.imread(str(p))) for p in sorted(OPENCV.glob("img_0*.jpg"))]
    assert all(i.ndim == 3 for i in imgs)
    blank = np.full_like(imgs[0], 128)
    frames = [imgs[0], imgs[0], imgs[1], cv2.GaussianBlur(imgs[1], (0, 0), 0.8), imgs[2], blank, imgs[3]]
    path = tmp_path / "board.avi"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 5.0, (640, 480))
    for f in frames:
        vw.write(f)
    vw.release()
    r = invoke_cli(["calibrate", path, "--board", BOARD, "--json"])
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    why = {int(x["frame"].rsplit("#", 1)[1]): x["reason"] for x in s["rejected"]}
    assert why[1].startswith("duplicate of")
    assert why[3].startswith("blurred")
    assert why[5].startswith("no ChArUco corners")
    assert sorted(set(range(7)) - set(why)) == [0, 2, 4, 6]
    assert s["cameras"][0]["frames"] == 4


def test_bad_interpolate_flag_exit_2():
    r = invoke_cli(["calibrate", OPENCV / "img_00.jpg", "--board", BOARD, "--interpolate", "spline"])
    assert r.exit_code == 2
    assert "--interpolate" in r.stderr and "aruco-calib" in r.stderr


def test_fix_principal_point_and_aspect_ratio_flags():
    """OpenCV's CALIB_FIX_PRINCIPAL_POINT and CALIB_FIX_ASPECT_RATIO: cx, cy at the image
    centre and fx = fy, listed as held. Not defaults: this camera's principal point lies
    38 px below the centre (OpenCV's cy 277.8), and holding it there moves fx to 515 px
    (+14 %, 4 sigma) while the RMS hardly grows (0.183 -> 0.189 px: each photograph's pose
    absorbs the principal point)."""
    imgs = sorted(OPENCV.glob("img_0*.jpg"))
    r = invoke_cli(["calibrate", *imgs, "--board", BOARD, "--json", "--fix-principal-point", "--fix-aspect-ratio"])
    assert r.exit_code == 0, r.stderr
    (cam,) = json.loads(r.stdout)["cameras"]
    assert (cam["cx"], cam["cy"]) == (319.5, 239.5)
    assert cam["fx"] == cam["fy"]
    assert cam["held"][:3] == ["cx", "cy", "k1"] or cam["held"][:2] == ["cx", "cy"]
    assert "aspect" in cam["held"] and cam["std"]["fx"] == cam["std"]["fy"] > 0
    assert cam["fx"] > REF["fx"] + 3 * 15.9 and cam["rms_px"] <= 0.25
