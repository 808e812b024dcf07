"""Float64 forward projection of camera-space points by COLMAP's camera models, as COLMAP
documents them (the reference that clrf's pixel -> ray undistortion is tested against).

Written model by model from the published equations, sharing no code with
``clrf.data.camera_models`` (which inverts them). Camera axes are OpenCV's: x right, y down, z
forward; (u, v) = (x, y) / z are the normalised coordinates; COLMAP adds a distortion offset
(du, dv) and maps to pixels with the focal lengths and the principal point; the centre of the
top-left pixel is at (0.5, 0.5).

    SIMPLE_PINHOLE f, cx, cy               du = dv = 0, fx = fy = f
    PINHOLE        fx, fy, cx, cy          du = dv = 0
    SIMPLE_RADIAL  f, cx, cy, k            radial = k r^2;             du = u radial
    RADIAL         f, cx, cy, k1, k2       radial = k1 r^2 + k2 r^4;   du = u radial
    OPENCV         fx, fy, cx, cy, k1, k2, p1, p2
                   radial = k1 r^2 + k2 r^4
                   du = u radial + 2 p1 u v + p2 (r^2 + 2 u^2)
                   dv = v radial + 2 p2 u v + p1 (r^2 + 2 v^2)
    FULL_OPENCV    fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6
                   radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
                   du = u radial + 2 p1 u v + p2 (r^2 + 2 u^2) - u, dv likewise
    OPENCV_FISHEYE fx, fy, cx, cy, k1, k2, k3, k4
                   theta = atan(r), theta_d = theta (1 + k1 t^2 + k2 t^4 + k3 t^6 + k4 t^8)
                   du = u theta_d / r - u, dv = v theta_d / r - v
    SIMPLE_RADIAL_FISHEYE f, cx, cy, k     theta_d = theta (1 + k theta^2)
    RADIAL_FISHEYE f, cx, cy, k1, k2       theta_d = theta (1 + k1 theta^2 + k2 theta^4)

with r^2 = u^2 + v^2; in every case x_pixel = fx (u + du) + cx, y_pixel = fy (v + dv) + cy.
"""
from __future__ import annotations

import numpy as np


def _fisheye_offset(u, v, ks):
    r = np.sqrt(u * u + v * v)
    theta = np.arctan(r)
    t2 = theta * theta
    poly = np.zeros_like(theta)
    for i, k in enumerate(ks):             # sum k_i theta^(2 i + 2)
        poly = poly + k * t2 ** (i + 1)
    theta_d = theta * (1.0 + poly)
    safe = np.where(r > 1e-15, r, 1.0)
    scale = np.where(r > 1e-15, theta_d / safe, 1.0)
    return u * scale - u, v * scale - v


def project(model: str, params, points_cam) -> np.ndarray:
    """Pixels [..., 2] of camera-space points ``points_cam`` [..., 3] (OpenCV axes, z > 0)
    through COLMAP camera ``model`` with ``params`` in COLMAP's order.

    Example: project("PINHOLE", [10, 10, 5, 5], [[0, 0, 1]]) -> [[5, 5]].
    """
    p = [float(x) for x in params]
    X = np.asarray(points_cam, np.float64)
    u, v = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    r2 = u * u + v * v
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE",
                 "RADIAL_FISHEYE"):
        fx = fy = p[0]
        cx, cy, extra = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy, extra = p[0], p[1], p[2], p[3], p[4:]
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        du = dv = np.zeros_like(u)
    elif model == "SIMPLE_RADIAL":
        radial = extra[0] * r2
        du, dv = u * radial, v * radial
    elif model == "RADIAL":
        radial = extra[0] * r2 + extra[1] * r2 * r2
        du, dv = u * radial, v * radial
    elif model == "OPENCV":
        k1, k2, p1, p2 = extra
        radial = k1 * r2 + k2 * r2 * r2
        du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
    elif model == "FULL_OPENCV":
        k1, k2, p1, p2, k3, k4, k5, k6 = extra
        r4, r6 = r2 * r2, r2 * r2 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        du = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u) - u
        dv = v * radial + 2 * p2 * u * v + p1 * (r2 + 2 * v * v) - v
    elif model in ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        du, dv = _fisheye_offset(u, v, extra)
    else:
        raise ValueError(f"reference projection: no model {model!r}")
    return np.stack([fx * (u + du) + cx, fy * (v + dv) + cy], -1)
