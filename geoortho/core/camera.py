"""Camera model: intrinsics, attitude → rotation, projection and back-projection.

Conventions (written once, here):

* World frame: the projected CRS, x east, y north, z up (metres).
* Camera frame: OpenCV's — x right, y down, z forward along the optical axis.
* Attitude: the drone makers' convention. ``yaw_deg`` clockwise from north,
  ``pitch_deg`` −90 = looking straight down, 0 = at the horizon,
  ``roll_deg`` right side down positive. Applied as yaw, then pitch, then roll
  (aerospace Z-Y-X). At yaw 0, pitch −90, roll 0 the top of the image points
  north and its right edge east.
* Pixels: (0, 0) is the *centre* of the top-left pixel (OpenCV, and what
  OpenDroneMap/OpenSfM assume for gcp_list.txt). The image spans
  −0.5 .. width−0.5.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from geoortho.core.gsd import focal_length_px

__all__ = [
    "Intrinsics",
    "Pose",
    "PosedCamera",
    "rotation_from_ypr",
    "ypr_from_rotation",
    "project_points",
    "pixel_rays",
    "undistort_pixels",
    "in_frame",
]

# Camera axes (x right, y down, z forward) expressed in the body frame
# (forward, right, down): x_cam = right, y_cam = down, z_cam = forward.
_BODY_FROM_CAM = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# NED (north, east, down) to ENU (east, north, up).
_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV (Brown–Conrady) distortion.

    Parameters
    ----------
    width_px, height_px
        Image size as decoded (not as EXIF claims).
    focal_px
        Focal length in pixels (square pixels).
    cx_px, cy_px
        Principal point, pixel-centre convention; ``None`` → image centre.
    distortion
        OpenCV ``(k1, k2, p1, p2, k3)``; empty for none.
    """

    width_px: int
    height_px: int
    focal_px: float
    cx_px: float = float("nan")
    cy_px: float = float("nan")
    distortion: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if np.isnan(self.cx_px):
            object.__setattr__(self, "cx_px", (self.width_px - 1) / 2.0)
        if np.isnan(self.cy_px):
            object.__setattr__(self, "cy_px", (self.height_px - 1) / 2.0)

    @classmethod
    def from_sensor(
        cls,
        width_px: int,
        height_px: int,
        focal_mm: float,
        sensor_width_mm: float,
        distortion: tuple[float, ...] = (),
    ) -> Intrinsics:
        """Intrinsics from the physical focal length and the sensor width spanned by the image width."""
        return cls(width_px, height_px, focal_length_px(focal_mm, sensor_width_mm, width_px), distortion=distortion)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.focal_px, 0, self.cx_px], [0, self.focal_px, self.cy_px], [0, 0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        d = np.zeros(5)
        d[: len(self.distortion)] = self.distortion
        return d

    @property
    def has_distortion(self) -> bool:
        return any(abs(c) > 0 for c in self.distortion)

    def border_pixels(self, per_side: int = 8) -> np.ndarray:
        """Points along the image border, clockwise from the top-left corner, (4*per_side, 2)."""
        w, h = self.width_px - 0.5, self.height_px - 0.5
        s = np.linspace(0.0, 1.0, per_side, endpoint=False)
        top = np.c_[-0.5 + s * self.width_px, np.full_like(s, -0.5)]
        right = np.c_[np.full_like(s, w), -0.5 + s * self.height_px]
        bottom = np.c_[w - s * self.width_px, np.full_like(s, h)]
        left = np.c_[np.full_like(s, -0.5), h - s * self.height_px]
        return np.vstack([top, right, bottom, left])


@dataclass(frozen=True, eq=False)
class Pose:
    """Camera centre (world, metres) and rotation world-from-camera (3×3)."""

    center: np.ndarray
    rotation: np.ndarray = field(repr=False)

    @classmethod
    def from_ypr(
        cls, center: tuple[float, float, float] | np.ndarray, yaw_deg: float, pitch_deg: float, roll_deg: float
    ) -> Pose:
        return cls(np.asarray(center, dtype=float), rotation_from_ypr(yaw_deg, pitch_deg, roll_deg))


def rotation_from_ypr(
    yaw_deg: float | np.ndarray, pitch_deg: float | np.ndarray, roll_deg: float | np.ndarray
) -> np.ndarray:
    """World(ENU)-from-camera rotation for drone yaw/pitch/roll in degrees.

    Scalars give (3, 3); arrays of N give (N, 3, 3).

    >>> R = rotation_from_ypr(0, -90, 0)   # nadir, image top to the north
    >>> np.round(R @ [0, 0, 1], 6).tolist()   # optical axis: down
    [0.0, 0.0, -1.0]
    >>> np.round(R @ [0, -1, 0], 6).tolist()  # image up: north
    [0.0, 1.0, 0.0]
    """
    y, p, r = (np.radians(np.asarray(a, dtype=float)) for a in (yaw_deg, pitch_deg, roll_deg))
    y, p, r = np.broadcast_arrays(y, p, r)
    cy, sy, cp, sp, cr, sr = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    # NED-from-body, Z(yaw) Y(pitch) X(roll).
    m = np.empty(y.shape + (3, 3))
    m[..., 0, 0] = cy * cp
    m[..., 0, 1] = cy * sp * sr - sy * cr
    m[..., 0, 2] = cy * sp * cr + sy * sr
    m[..., 1, 0] = sy * cp
    m[..., 1, 1] = sy * sp * sr + cy * cr
    m[..., 1, 2] = sy * sp * cr - cy * sr
    m[..., 2, 0] = -sp
    m[..., 2, 1] = cp * sr
    m[..., 2, 2] = cp * cr
    return np.asarray(_ENU_FROM_NED @ m @ _BODY_FROM_CAM)


def ypr_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_ypr` (degrees; yaw in [-180, 180))."""
    m = _ENU_FROM_NED.T @ np.asarray(rotation) @ _BODY_FROM_CAM.T
    pitch = np.degrees(np.arcsin(np.clip(-m[2, 0], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(m[1, 0], m[0, 0]))
    roll = np.degrees(np.arctan2(m[2, 1], m[2, 2]))
    return float((yaw + 180.0) % 360.0 - 180.0), float(pitch), float(roll)


def project_points(points: np.ndarray, intrinsics: Intrinsics, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) to pixels (N, 2); also return depth along the axis (N,).

    Points behind the camera get NaN pixels.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    cam = (pts - pose.center) @ pose.rotation  # = R^T (p - c), row-wise
    depth = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = cam[:, :2] / depth[:, None]
    if intrinsics.has_distortion:
        pix, _ = cv2.projectPoints(
            np.c_[xn, np.ones(len(xn))].reshape(-1, 1, 3).astype(np.float64),
            np.zeros(3),
            np.zeros(3),
            intrinsics.matrix,
            intrinsics.dist_coeffs,
        )
        pix = pix.reshape(-1, 2)
    else:
        pix = xn * intrinsics.focal_px + [intrinsics.cx_px, intrinsics.cy_px]
    pix[depth <= 0] = np.nan
    return pix, depth


def undistort_pixels(pixels: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Pixels (N, 2) → normalized undistorted image coordinates (N, 2)."""
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    if not intrinsics.has_distortion:
        return (px - [intrinsics.cx_px, intrinsics.cy_px]) / intrinsics.focal_px
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    # OpenCV 4 spells the variant with termination criteria undistortPointsIter; 5 folds it in.
    und_fn = getattr(cv2, "undistortPointsIter", None)
    if und_fn is not None:
        und = und_fn(px.reshape(-1, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs, None, None, crit)
    else:
        und = cv2.undistortPoints(
            px.reshape(-1, 1, 2), intrinsics.matrix, intrinsics.dist_coeffs, None, None, None, crit
        )
    return np.asarray(und).reshape(-1, 2)


def pixel_rays(pixels: np.ndarray, intrinsics: Intrinsics, pose: Pose) -> np.ndarray:
    """World unit direction (N, 3) of the ray through each pixel."""
    xn = undistort_pixels(pixels, intrinsics)
    d = np.c_[xn, np.ones(len(xn))] @ pose.rotation.T
    return np.asarray(d / np.linalg.norm(d, axis=1, keepdims=True))


def in_frame(
    x: float | np.ndarray,
    y: float | np.ndarray,
    width_px: float,
    height_px: float,
    margin_x_px: float = 0.0,
    margin_y_px: float = 0.0,
) -> bool | np.ndarray:
    """Whether pixels lie in the image (−0.5 .. size−0.5, pixel-centre convention), ``margin``
    pixels in from each side (a negative margin reaches outside)."""
    return (
        (-0.5 + margin_x_px <= x)
        & (x <= width_px - 0.5 - margin_x_px)
        & (-0.5 + margin_y_px <= y)
        & (y <= height_px - 0.5 - margin_y_px)
    )


@dataclass(frozen=True, eq=False)
class PosedCamera:
    """One camera posed in a CRS: intrinsics (with distortion) and pose, and the photo file it
    took, if any. The one posed-camera type: footprints, gcp-find, the orthophoto, the dense
    surface and the flight plan share it, whether the pose was measured (SfM), recorded (EXIF)
    or planned (no file: ``path`` None)."""

    intrinsics: Intrinsics
    pose: Pose
    name: str = ""
    path: Path | None = None

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) → pixels (N, 2) (pixel-centre convention) and depth (N,)."""
        return project_points(xyz, self.intrinsics, self.pose)

    @property
    def file(self) -> Path:
        """The photo's file; a planned camera has none."""
        if self.path is None:
            raise ValueError(f"camera {self.name!r} has no photo file")
        return self.path
