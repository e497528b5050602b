"""Camera images as a pinhole camera sees them: lens distortion removed and depth registered to the colour camera.

`undistort_maps` builds OpenCV's remap tables for a CameraInfo's plumb_bob (k1 k2 p1 p2 k3) or rational_polynomial
(k1 k2 p1 p2 k3 k4 k5 k6) model, keeping K as the undistorted camera's matrix; colour is resampled bilinearly, depth
with the nearest pixel (blending depth across an edge invents surfaces). `register_depth` moves a depth image into
another camera: back-project with the depth camera's K, transform, project with the colour camera's K and keep the
nearest surface where several land on one pixel (a z-buffer), all vectorised with numpy.
"""

from __future__ import annotations

import cv2
import numpy as np

DISTORTION_COEFFICIENTS = {"plumb_bob": 5, "rational_polynomial": 8}
"""The CameraInfo distortion models OpenCV undistorts here, with their coefficient counts."""


def distortion_problem(model: str, coefficients: np.ndarray) -> str | None:
    """What keeps a CameraInfo distortion from being undistorted, or None (also for all-zero coefficients of any
    model: a pinhole camera)."""
    D = np.asarray(coefficients, dtype=np.float64)
    if D.size and not np.isfinite(D).all():
        return f"distortion coefficients {D.tolist()} are not finite"
    if not np.any(D):
        return None
    if model not in DISTORTION_COEFFICIENTS:
        known = ", ".join(DISTORTION_COEFFICIENTS)
        return f"distortion model {model!r} is not supported ({known}); record rectified images instead"
    if D.size < DISTORTION_COEFFICIENTS[model]:
        return f"{model} distortion needs {DISTORTION_COEFFICIENTS[model]} coefficients, got {D.size}"
    return None


def undistort_maps(K: np.ndarray, D: np.ndarray, size_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (two (H, W) float32 arrays) that undistort an image of `size_wh` to the pinhole camera K."""
    K = np.asarray(K, dtype=np.float64)
    return cv2.initUndistortRectifyMap(K, np.asarray(D, dtype=np.float64), None, K, size_wh, cv2.CV_32FC1)


def remap_colour(rgb: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(H, W, 3) uint8 resampled bilinearly through `maps`; black outside the source image."""
    return cv2.remap(rgb, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def remap_depth(depth_m: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(H, W) float32 metres resampled at the nearest pixel through `maps`; NaN (no return) outside the image."""
    return cv2.remap(
        depth_m.astype(np.float32, copy=False),
        maps[0],
        maps[1],
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )


def register_depth(
    depth_m: np.ndarray, K_depth: np.ndarray, T_colour_depth: np.ndarray, K_colour: np.ndarray, size_wh: tuple[int, int]
) -> np.ndarray:
    """Depth (H_d, W_d) float32 metres of the depth camera → (H, W) float32 metres along the colour camera's z axis.

    Each valid depth pixel is back-projected with `K_depth`, moved by `T_colour_depth` (4, 4) and projected with
    `K_colour` to its nearest pixel; of several points on one pixel the nearest wins. Pixels nothing lands on are
    NaN (a lower-resolution depth camera leaves gaps; no hole is filled)."""
    width, height = size_wh
    v, u = np.nonzero(np.isfinite(depth_m) & (depth_m > 0))
    z = depth_m[v, u].astype(np.float64)
    Kd = np.asarray(K_depth, dtype=np.float64)
    points = np.stack([(u - Kd[0, 2]) / Kd[0, 0] * z, (v - Kd[1, 2]) / Kd[1, 1] * z, z], axis=-1)
    T = np.asarray(T_colour_depth, dtype=np.float64)
    points = points @ T[:3, :3].T + T[:3, 3]
    out = np.full((height, width), np.nan, dtype=np.float32)
    Z = points[:, 2]
    front = Z > 1e-6
    points, Z = points[front], Z[front]
    Kc = np.asarray(K_colour, dtype=np.float64)
    uc = np.rint(Kc[0, 0] * points[:, 0] / Z + Kc[0, 2])
    vc = np.rint(Kc[1, 1] * points[:, 1] / Z + Kc[1, 2])
    inside = (uc >= 0) & (uc < width) & (vc >= 0) & (vc < height)
    pixel = vc[inside].astype(np.int64) * width + uc[inside].astype(np.int64)
    Z = Z[inside]
    order = np.lexsort((Z, pixel))  # by pixel, nearest first within each pixel
    pixel, Z = pixel[order], Z[order]
    first = np.r_[True, pixel[1:] != pixel[:-1]]
    out.reshape(-1)[pixel[first]] = Z[first]
    return out
