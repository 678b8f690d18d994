"""The camera path (a real VideoCapture over a video file) and the ArUco valve angle."""

import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.robot_bridge.camera import ArucoAngle, Camera, calibrated, servo_angle
from services.robot_bridge.config import AngleConfig, CameraConfig


def _video(path: Path, frames: int = 20, size: tuple[int, int] = (160, 120)) -> None:
    """Frame i is a flat BGR colour whose green level is 10 * i, so a frame knows its index."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, size)
    assert writer.isOpened()
    for i in range(frames):
        frame = np.zeros((size[1], size[0], 3), np.uint8)
        frame[..., 0] = 200  # blue, in OpenCV's BGR order
        frame[..., 1] = 10 * i
        writer.write(frame)
    writer.release()


def test_each_observation_drops_stale_frames_and_is_84x84_rgb(tmp_path: Path) -> None:
    path = tmp_path / "cam.avi"
    _video(path)
    cam = Camera(CameraConfig(drop_frames=3, image_size=84), source=str(path))
    try:
        seen = []
        for _ in range(3):
            obs, bgr = cam.observe()
            assert obs.shape == (3, 84, 84) and obs.dtype == np.uint8
            assert bgr.shape == (120, 160, 3)
            assert abs(int(obs[2].mean()) - 200) < 8 and int(obs[0].mean()) < 8  # blue went to RGB's last
            seen.append(round(float(obs[1].mean()) / 10))
        assert seen == [3, 7, 11]  # three stale frames dropped before each one read
    finally:
        cam.close()


def _marker_scene(degrees: float, marker_id: int = 7) -> np.ndarray:
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, 120)
    scene = np.full((320, 320), 255, np.uint8)
    scene[100:220, 100:220] = marker
    # OpenCV's positive angle turns counter-clockwise on screen.
    turn = cv2.getRotationMatrix2D((160, 160), degrees, 1.0)
    scene = cv2.warpAffine(scene, turn, (320, 320), borderValue=255)
    return cv2.cvtColor(scene, cv2.COLOR_GRAY2BGR)


@pytest.mark.parametrize("degrees", [0.0, 37.0, 135.0, 200.0, 350.0])
def test_aruco_angle_follows_the_marker(degrees: float) -> None:
    sensor = ArucoAngle(AngleConfig(source="aruco", aruco_id=7))
    angle = sensor.angle(_marker_scene(degrees))
    assert angle is not None
    error = (angle - math.radians(degrees) + math.pi) % (2 * math.pi) - math.pi
    assert abs(error) < math.radians(2.0)


def test_aruco_angle_is_none_without_its_marker() -> None:
    assert ArucoAngle(AngleConfig(aruco_id=3)).angle(_marker_scene(10.0, marker_id=7)) is None
    assert ArucoAngle(AngleConfig(aruco_id=3)).angle(np.full((100, 100, 3), 255, np.uint8)) is None


def test_calibration_sets_zero_and_direction() -> None:
    config = AngleConfig(zero_deg=30.0, direction=-1)
    assert calibrated(30.0, config) == pytest.approx(0.0)
    assert calibrated(20.0, config) == pytest.approx(math.radians(10.0))
    assert calibrated(40.0, config) == pytest.approx(math.radians(350.0))
    assert servo_angle(512, AngleConfig(zero_deg=150.0)) == pytest.approx(0.0, abs=1e-9)


def test_calibrate_reads_the_raw_marker_angle(tmp_path: Path, capsys) -> None:
    from services.robot_bridge import operate

    path = tmp_path / "marker.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (320, 320))
    for _ in range(10):
        writer.write(_marker_scene(40.0, marker_id=0))
    writer.release()
    example = Path(operate.__file__).with_name("example.toml")
    config = tmp_path / "gripper.toml"
    config.write_text(example.read_text().replace("drop_frames = 4", "drop_frames = 0"))
    operate.main(["calibrate", "--config", str(config), "--samples", "5", "--source", str(path)])
    out = capsys.readouterr().out
    reading = float(out.split("angle.zero_deg = ")[1])
    assert abs(reading - 40.0) < 2.0


def test_a_calibration_that_never_sees_its_marker_is_one_error_line(tmp_path: Path, capsys) -> None:
    from services.robot_bridge import operate

    path = tmp_path / "no-marker.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30, (320, 320))
    for _ in range(10):
        writer.write(np.full((320, 320, 3), 255, np.uint8))
    writer.release()
    example = Path(operate.__file__).with_name("example.toml")
    config = tmp_path / "gripper.toml"
    config.write_text(example.read_text().replace("drop_frames = 4", "drop_frames = 0"))
    with pytest.raises(SystemExit) as exited:
        operate.main(["calibrate", "--config", str(config), "--samples", "3", "--source", str(path)])
    out, err = capsys.readouterr()
    assert exited.value.code == 1 and out == "", out
    assert err.startswith("calibrate: error: the valve angle was never read") and err.count("\n") == 1, err


@pytest.mark.parametrize("camera", ["file", "index"])
def test_a_calibration_whose_camera_cannot_be_opened_is_one_line_and_exit_1(
    tmp_path: Path, camera: str
) -> None:
    """OpenCV's own lines about the camera it could not open are not printed beside the error."""
    from services.robot_bridge import operate

    text = Path(operate.__file__).with_name("example.toml").read_text()
    if camera == "file":
        where, extra = repr(str(tmp_path / "missing.avi")), ["--source", str(tmp_path / "missing.avi")]
    else:  # a camera index this machine has no device for
        index = next(i for i in range(63, 0, -1) if not Path(f"/dev/video{i}").exists())
        where, extra, text = repr(index), [], text.replace("index = 0", f"index = {index}")
    config = tmp_path / "gripper.toml"
    config.write_text(text)
    argv = ["calibrate", "--config", str(config), "--samples", "1", *extra]
    done = subprocess.run([sys.executable, "-m", "services.robot_bridge.operate", *argv],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, done.stderr
    assert done.stderr.splitlines() == [f"calibrate: error: cannot open camera {where}"], done.stderr
