"""The webcam and the valve angle: OpenCV capture, 84x84 RGB observations, ArUco or servo angle.

Needs `opencv-contrib-python-headless` (the contrib build holds the ArUco module); without it,
building a `Camera` or `ArucoAngle` fails with `CameraUnavailable` saying what to install.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from services.robot_bridge import xl320
from services.robot_bridge.config import AngleConfig, CameraConfig

INSTALL_HINT = "pip install opencv-contrib-python-headless==5.0.0.93"


class CameraUnavailable(RuntimeError):
    """OpenCV is missing, or the camera cannot be opened or read."""


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as e:
        raise CameraUnavailable(f"the camera and ArUco angle need OpenCV: {INSTALL_HINT}") from e
    return cv2


def to_observation(bgr: np.ndarray, image_size: int) -> np.ndarray:
    """A BGR camera frame as the agent's (3, size, size) uint8 RGB frame (area interpolation)."""
    cv2 = _cv2()
    small = cv2.resize(bgr, (image_size, image_size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(cv2.cvtColor(small, cv2.COLOR_BGR2RGB).transpose(2, 0, 1))


class Camera:
    """A VideoCapture at the configured resolution; each frame is from after the last action.

    `source` overrides the configured device index (a video file path, for tests).
    """

    def __init__(self, config: CameraConfig, source: int | str | None = None) -> None:
        cv2 = _cv2()
        self.config = config
        where = config.index if source is None else source
        # OpenCV logs lines of its own for a camera it cannot open (from each backend it tries): the
        # error below says it once.
        level = cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
        try:
            self._capture = cv2.VideoCapture(where)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if not self._capture.isOpened():
            raise CameraUnavailable(f"cannot open camera {where!r}")
        self._capture.set(cv2.CAP_PROP_FRAME_WIDTH, config.width)
        self._capture.set(cv2.CAP_PROP_FRAME_HEIGHT, config.height)
        # A driver that honours it keeps one frame; the rest are dropped by `frame()` anyway.
        self._capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)

    def frame(self) -> np.ndarray:
        """The newest full-resolution BGR frame: stale buffered frames are grabbed and dropped."""
        for _ in range(self.config.drop_frames):
            self._capture.grab()
        ok, bgr = self._capture.read()
        if not ok or bgr is None:
            raise CameraUnavailable("the camera returned no frame")
        return bgr

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        """(observation (3, size, size) RGB uint8, the full BGR frame it came from)."""
        bgr = self.frame()
        return to_observation(bgr, self.config.image_size), bgr

    def close(self) -> None:
        self._capture.release()


def calibrated(raw_deg: float, config: AngleConfig) -> float:
    """A raw angle reading (degrees) as the valve angle in [0, 2 pi) after calibration."""
    return math.radians(config.direction * (raw_deg - config.zero_deg)) % (2.0 * math.pi)


class ArucoAngle:
    """The valve angle from an ArUco marker fixed on the valve, seen by the camera."""

    def __init__(self, config: AngleConfig) -> None:
        cv2 = _cv2()
        if not hasattr(cv2, "aruco"):
            raise CameraUnavailable(f"this OpenCV has no ArUco module (the contrib build): {INSTALL_HINT}")
        self.config = config
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.aruco_dictionary))
        self._detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())

    def raw_degrees(self, bgr: np.ndarray) -> float | None:
        """The marker's rotation in the image (degrees, counter-clockwise as seen), None if unseen."""
        corners, ids, _ = self._detector.detectMarkers(bgr)
        if ids is None:
            return None
        for marker_corners, marker_id in zip(corners, ids.ravel(), strict=True):
            if int(marker_id) == self.config.aruco_id:
                (x0, y0), (x1, y1) = marker_corners[0][0], marker_corners[0][1]
                # Image rows grow downward: negate dy so counter-clockwise on screen is positive.
                return math.degrees(math.atan2(-(y1 - y0), x1 - x0))
        return None

    def angle(self, bgr: np.ndarray) -> float | None:
        raw = self.raw_degrees(bgr)
        return None if raw is None else calibrated(raw, self.config)


def servo_angle(present_position: int, config: AngleConfig) -> float:
    """The valve angle from the valve servo's present position (its 300 degrees of range)."""
    return calibrated(present_position * xl320.DEGREES_PER_STEP, config)
