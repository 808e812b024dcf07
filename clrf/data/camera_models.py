"""Lens distortion: the camera models of COLMAP and instant-ngp mapped onto two families.

Points are OpenCV normalised image coordinates, ``x = (u - cx) / fx``, ``y = (v - cy) / fy``
(y down); the undistorted point of a camera-space point (X, Y, Z), Z > 0 forward, is
(X / Z, Y / Z). Every model here is one of two families of :class:`Distortion`:

- ``radtan``: OpenCV's rational radial-tangential model, coeffs (k1, k2, p1, p2, k3, k4, k5, k6)
  in OpenCV's order. With r2 = x^2 + y^2::

      radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
      x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
      y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

  COLMAP's SIMPLE_RADIAL (k), RADIAL (k1, k2), OPENCV (k1, k2, p1, p2) and FULL_OPENCV (all
  eight) are this family with the missing terms 0.
- ``fisheye``: the equidistant fisheye of OpenCV (COLMAP's OPENCV_FISHEYE), coeffs
  (k1, k2, k3, k4). With r = |(x, y)| and theta = atan(r), the angle off the optical axis::

      theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
      (x_d, y_d) = (theta_d / r) (x, y)

  COLMAP's SIMPLE_RADIAL_FISHEYE (k) and RADIAL_FISHEYE (k1, k2) are this family.

Undistortion (pixel -> ray) is Newton's method: a 2x2 analytic Jacobian for ``radtan``, the
scalar equation in theta for ``fisheye`` (then r = tan theta). Neither inverse exists past the
radius where the model folds over, so :func:`check_camera` tells a loader whether the whole
image lies inside the invertible region.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEWTON_ITERS = 50         # cap; real lenses converge to 1e-14 in < 8 from the distorted point
NEWTON_TOL = 1e-14        # stop once the largest update is below this (normalised units)
SMALL_R = 1e-12           # below this radius the fisheye scale theta_d / r is 1 (its limit)
# The rays clrf traces have camera-space z = -1, which cannot hold a ray at or beyond 90 degrees
# off the axis; fisheye images are accepted up to this angle at their border.
FISHEYE_MAX_THETA = np.deg2rad(89.0)
ROUNDTRIP_TOL = 1e-9      # normalised units: distort(undistort(p)) must return p this closely
FOLD_SAMPLES = 64         # points checked for a fold on each line from the centre to the border

FAMILIES = {"radtan": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
            "fisheye": ("k1", "k2", "k3", "k4")}

# COLMAP model name -> (model id, parameter names in file order). Intrinsics come from
# f / fx, fy, cx, cy; the other parameters name the family's coefficients they set.
MODELS = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k1")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "OPENCV_FISHEYE": (5, ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")),
    "FULL_OPENCV": (6, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5",
                        "k6")),
    "SIMPLE_RADIAL_FISHEYE": (8, ("f", "cx", "cy", "k1")),
    "RADIAL_FISHEYE": (9, ("f", "cx", "cy", "k1", "k2")),
}
FISHEYE_MODELS = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")
# COLMAP models clrf refuses by name (id -> name, parameter count)
UNSUPPORTED = {7: ("FOV", 5), 10: ("THIN_PRISM_FISHEYE", 12),
               11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
INTRINSIC_NAMES = ("f", "fx", "fy", "cx", "cy")


@dataclass(frozen=True)
class Distortion:
    """One lens distortion: ``family`` ("radtan" or "fisheye") and its ``coeffs`` in the order
    of ``FAMILIES[family]`` (8 or 4 floats)."""

    family: str
    coeffs: tuple

    def __post_init__(self):
        if self.family not in FAMILIES:
            raise ValueError(f"distortion family: expected one of {', '.join(FAMILIES)}, got "
                             f"{self.family!r}")
        c = tuple(float(v) for v in self.coeffs)
        if len(c) != len(FAMILIES[self.family]) or not all(np.isfinite(c)):
            raise ValueError(f"{self.family} distortion: expected {len(FAMILIES[self.family])} "
                             f"finite coefficients {FAMILIES[self.family]}, got {self.coeffs}")
        object.__setattr__(self, "coeffs", c)

    @classmethod
    def radtan(cls, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0, k4=0.0, k5=0.0, k6=0.0):
        return cls("radtan", (k1, k2, p1, p2, k3, k4, k5, k6))

    @classmethod
    def fisheye(cls, k1=0.0, k2=0.0, k3=0.0, k4=0.0):
        return cls("fisheye", (k1, k2, k3, k4))

    @property
    def is_identity(self) -> bool:
        """True for a radial-tangential model with every coefficient 0 (a fisheye with zero
        coefficients is still the equidistant projection, not a pinhole)."""
        return self.family == "radtan" and not any(self.coeffs)

    def named(self) -> dict:
        return dict(zip(FAMILIES[self.family], self.coeffs))

    def to_json(self) -> dict:
        return {"family": self.family, "coeffs": list(self.coeffs)}


def as_distortion(d):
    """None, a :class:`Distortion`, its ``to_json()`` dict, or a legacy OpenCV (k1, k2, p1, p2)
    sequence -> a Distortion, or None for no distortion."""
    if d is None or isinstance(d, Distortion):
        return None if d is None or d.is_identity else d
    if isinstance(d, dict):
        return as_distortion(Distortion(d["family"], tuple(d["coeffs"])))
    c = np.asarray(d, np.float64).reshape(-1)
    if c.shape != (4,):
        raise ValueError(f"distortion: expected a Distortion or OpenCV (k1, k2, p1, p2), got "
                         f"shape {np.shape(d)}")
    return as_distortion(Distortion.radtan(*c))


def from_colmap(model: str, params):
    """COLMAP camera ``model`` and its ``params`` -> (intrinsics float64 [4] (fx, fy, cx, cy),
    Distortion or None). Raises KeyError for a model not in MODELS and ValueError for a wrong
    parameter count."""
    names = MODELS[model][1]
    if len(params) != len(names):
        raise ValueError(f"{model} needs {len(names)} parameters ({', '.join(names)}), got "
                         f"{len(params)}")
    p = dict(zip(names, map(float, params)))
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    intr = np.array([fx, fy, p["cx"], p["cy"]])
    k = {n: v for n, v in p.items() if n not in INTRINSIC_NAMES}
    dist = Distortion.fisheye(**k) if model in FISHEYE_MODELS else Distortion.radtan(**k)
    return intr, as_distortion(dist)


# ---------------------------------------------------------------- the two families

def _radtan_terms(x, y, c):
    """radial, d radial / d r2, and the distorted point of the rational radial-tangential
    model at (x, y)."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    g = ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den
         - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return radial, g, xd, yd


def _radtan_jacobian(x, y, c):
    """d(x_d, y_d) / d(x, y) as its four entries (each the shape of x)."""
    _, _, p1, p2 = c[:4]
    radial, g, _, _ = _radtan_terms(x, y, c)
    a = radial + 2.0 * g * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    b = 2.0 * g * x * y + 2.0 * p1 * x + 2.0 * p2 * y
    d = radial + 2.0 * g * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    return a, b, b, d


def _theta_poly(theta, c):
    """theta_d(theta) and its derivative for fisheye coeffs c = (k1, k2, k3, k4)."""
    k1, k2, k3, k4 = c
    t2 = theta * theta
    poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
    dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
    return theta * poly, dpoly


def _fisheye_theta(theta_d, c, iters=NEWTON_ITERS):
    """theta with theta_d(theta) = ``theta_d``, by Newton's method from theta = theta_d."""
    theta = np.array(theta_d, np.float64)
    for _ in range(iters):
        f, df = _theta_poly(theta, c)
        step = (f - theta_d) / df
        theta = theta - step
        if float(np.max(np.abs(step), initial=0.0)) < NEWTON_TOL:
            break
    return theta


def distort(xy, distortion) -> np.ndarray:
    """Distorted normalised points [..., 2] of undistorted ones ``xy`` [..., 2] (float64).

    Example: distort([[0.1, 0.0]], (0.1, 0, 0, 0)) -> [[0.1001, 0.0]] (OpenCV k1 = 0.1).
    """
    d = as_distortion(distortion)
    xy = np.asarray(xy, np.float64)
    if d is None:
        return xy.copy()
    x, y = xy[..., 0], xy[..., 1]
    if d.family == "radtan":
        _, _, xd, yd = _radtan_terms(x, y, d.coeffs)
        return np.stack([xd, yd], -1)
    r = np.hypot(x, y)
    theta_d, _ = _theta_poly(np.arctan(r), d.coeffs)
    scale = np.where(r > SMALL_R, theta_d / np.maximum(r, SMALL_R), 1.0)
    return xy * scale[..., None]


def undistort(xy_d, distortion, iters: int = NEWTON_ITERS) -> np.ndarray:
    """Invert :func:`distort` by Newton's method, starting from the distorted point.

    radtan: (x, y) <- (x, y) - J^-1 (distort(x, y) - (x_d, y_d)), J the 2x2 Jacobian.
    fisheye: theta <- theta - (theta_d(theta) - |xy_d|) / theta_d'(theta), then
    (x, y) = xy_d tan(theta) / |xy_d|. Stops after ``iters`` steps or once the largest update
    is below NEWTON_TOL. Inside the region :func:`check_camera` accepts it converges to the
    unique inverse; outside it the result is whatever the iteration reached.
    """
    d = as_distortion(distortion)
    xy_d = np.asarray(xy_d, np.float64)
    if d is None:
        return xy_d.copy()
    if d.family == "fisheye":
        theta_d = np.hypot(xy_d[..., 0], xy_d[..., 1])
        theta = _fisheye_theta(theta_d, d.coeffs, iters)
        scale = np.where(theta_d > SMALL_R, np.tan(theta) / np.maximum(theta_d, SMALL_R), 1.0)
        return xy_d * scale[..., None]
    x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
    for _ in range(iters):
        _, _, fx, fy = _radtan_terms(x, y, d.coeffs)
        ex, ey = fx - xy_d[..., 0], fy - xy_d[..., 1]
        a, b, c, e = _radtan_jacobian(x, y, d.coeffs)
        det = a * e - b * c
        sx, sy = (e * ex - b * ey) / det, (a * ey - c * ex) / det
        x, y = x - sx, y - sy
        if max(float(np.max(np.abs(sx), initial=0.0)),
               float(np.max(np.abs(sy), initial=0.0))) < NEWTON_TOL:
            break
    return np.stack([x, y], -1)


def _border(intrinsics, H, W):
    """Normalised distorted coordinates of the outer edges of the image border [4 (W + H) + 4, 2]
    (the points of an image farthest from its centre lie on the border)."""
    fx, fy, cx, cy = np.asarray(intrinsics, np.float64)
    u = np.concatenate([np.arange(W + 1.0), np.zeros(H + 1), np.arange(W + 1.0),
                        np.full(H + 1, float(W))])
    v = np.concatenate([np.zeros(W + 1), np.arange(H + 1.0), np.full(W + 1, float(H)),
                        np.arange(H + 1.0)])
    return np.stack([(u - cx) / fx, (v - cy) / fy], -1)


def check_camera(distortion, intrinsics, H: int, W: int):
    """None when every pixel of an H x W image maps to exactly one ray, else the reason (str).

    The image must lie inside the region where the model is one-to-one: along the line from
    the image centre to each border point (undistorted), the Jacobian determinant of the
    radial-tangential model (or d theta_d / d theta of the fisheye) stays positive, Newton's
    result re-distorts to the border point within ROUNDTRIP_TOL, and a fisheye's border stays
    below FISHEYE_MAX_THETA off the axis.
    """
    d = as_distortion(distortion)
    if d is None:
        return None
    pd = _border(intrinsics, H, W)
    fold = ("undistortion does not converge at the image border (re-distortion error {:.3g} in "
            "normalised units): the coefficients fold the image over")
    s = np.linspace(0.0, 1.0, FOLD_SAMPLES)[:, None]
    if d.family == "fisheye":
        theta_d = np.hypot(pd[:, 0], pd[:, 1])
        theta = _fisheye_theta(theta_d, d.coeffs)
        err = float(np.max(np.abs(_theta_poly(theta, d.coeffs)[0] - theta_d)))
        if not np.isfinite(err) or err > ROUNDTRIP_TOL:
            return fold.format(err)
        if float(theta.max()) >= FISHEYE_MAX_THETA:
            return (f"the image border is {np.degrees(theta.max()):.1f} degrees off the optical "
                    f"axis; clrf traces rays up to {np.degrees(FISHEYE_MAX_THETA):.0f} degrees: "
                    f"crop the images")
        slope = _theta_poly(s * theta[None], d.coeffs)[1]              # [S, B]
    else:
        p = undistort(pd, d)
        err = float(np.max(np.abs(distort(p, d) - pd)))
        if not np.isfinite(err) or err > ROUNDTRIP_TOL:
            return fold.format(err)
        line = s[..., None] * p[None]                                 # [S, B, 2]
        a, b, c, e = _radtan_jacobian(line[..., 0], line[..., 1], d.coeffs)
        slope = a * e - b * c
    if float(slope.min()) <= 0.0:
        return ("the distortion folds over inside the image (its Jacobian is not positive "
                "between the centre and the border), so some pixels have two rays")
    return None
