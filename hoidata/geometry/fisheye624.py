"""The FISHEYE624 camera (Project Aria and Quest 3 cameras, as HOT3D-Clips calibrates them). Pure numpy.

The model, from its published definition (docs/datasets.md, "HOT3D-Clips"): an eye-frame point (x, y, z), OpenCV
axes, goes to

1. the arctan projection p = (x, y) / r * theta with r = |(x, y)| and theta = atan2(r, z): |p| is the angle in
   radians between the ray and +z, so rays up to and beyond 90 degrees have a place;
2. six radial terms in theta: u_r = p * (1 + k1 theta^2 + k2 theta^4 + ... + k6 theta^12);
3. two tangential and four thin-prism terms on u_r, with rho = |u_r|^2:
   x' = x + 2 p2 x y + p1 (rho + 2 x^2) + s1 rho + s2 rho^2,
   y' = y + 2 p1 x y + p2 (rho + 2 y^2) + s3 rho + s4 rho^2;
4. pixels (u, v) = (fx x' + cx, fy y' + cy), pixel centres at whole numbers (OpenCV's convention).

``projection_params`` holds 15 values (f, cx, cy, then the 12 coefficients: Aria, one focal length) or 16 (fx, fy,
cx, cy, then the 12: Quest 3). Unprojection inverts steps 2-3 by Newton's method on the analytic 2x2 Jacobian and
step 1 in closed form.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

N_COEFFS = 12  # k1..k6, p1, p2, s1..s4


@dataclass(frozen=True)
class Fisheye624:
    """One FISHEYE624 camera's intrinsics.

    Args:
        width, height: image size, pixels.
        fx, fy: focal lengths, pixels per radian near the axis.
        cx, cy: principal point, pixels (pixel centres at whole numbers).
        coeffs: (12,) k1..k6 (radial, in theta), p1, p2 (tangential), s1..s4 (thin prism).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    coeffs: tuple

    @classmethod
    def from_params(cls, params, width: int, height: int) -> Fisheye624:
        """A camera from HOT3D's ``projection_params``: 15 values (f, cx, cy, 12 coefficients) or 16 (fx, fy,
        cx, cy, 12 coefficients). Any other length is a ValueError."""
        values = [float(v) for v in params]
        if len(values) == 3 + N_COEFFS:
            f, cx, cy = values[:3]
            return cls(int(width), int(height), f, f, cx, cy, tuple(values[3:]))
        if len(values) == 4 + N_COEFFS:
            fx, fy, cx, cy = values[:4]
            return cls(int(width), int(height), fx, fy, cx, cy, tuple(values[4:]))
        raise ValueError(f"FISHEYE624 takes 15 or 16 projection_params, got {len(values)}")

    def params(self) -> list[float]:
        """``projection_params`` as HOT3D writes them: 15 values when fx == fy (Aria), else 16."""
        head = [self.fx, self.cx, self.cy] if self.fx == self.fy else [self.fx, self.fy, self.cx, self.cy]
        return [float(v) for v in head + list(self.coeffs)]

    def project(self, points: np.ndarray) -> np.ndarray:
        """Eye-frame points (..., 3), metres or any scale -> pixels (..., 2)."""
        q = distort(arctan_project(np.asarray(points, np.float64)), self.coeffs)
        return q * np.array([self.fx, self.fy]) + np.array([self.cx, self.cy])

    def unproject(self, pixels: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Pixels (..., 2) -> unit rays (..., 3) in the eye frame (Newton's method on the distortion)."""
        q = (np.asarray(pixels, np.float64) - np.array([self.cx, self.cy])) / np.array([self.fx, self.fy])
        return arctan_unproject(undistort(q, self.coeffs, iterations))

    def max_angle(self) -> float:
        """The largest angle from +z (radians) up to which the radial distortion keeps increasing: the field of
        view the model can be inverted in."""
        return float(radial_table(tuple(self.coeffs[:6]))[0][-1])


def arctan_project(points: np.ndarray, eps: float = 1e-300) -> np.ndarray:
    """(..., 3) -> (..., 2): the direction of (x, y) scaled to the ray's angle from +z (radians)."""
    x, y, z = np.moveaxis(points, -1, 0)
    r = np.hypot(x, y)
    scale = np.arctan2(r, z) / np.maximum(r, eps)
    return np.stack([x * scale, y * scale], axis=-1)


def arctan_unproject(p: np.ndarray) -> np.ndarray:
    """(..., 2) -> unit rays (..., 3): the inverse of :func:`arctan_project` for angles below pi."""
    theta = np.linalg.norm(p, axis=-1)
    s = np.sinc(theta / np.pi)  # sin(theta) / theta, 1 at theta = 0
    return np.stack([p[..., 0] * s, p[..., 1] * s, np.cos(theta)], axis=-1)


def _radial(s: np.ndarray, k) -> tuple[np.ndarray, np.ndarray]:
    """1 + sum k_i s^i and its derivative in s, for s = theta^2."""
    value, slope, power = np.ones_like(s), np.zeros_like(s), np.ones_like(s)
    for i, ki in enumerate(k, start=1):
        slope = slope + i * ki * power
        power = power * s
        value = value + ki * power
    return value, slope


def distort(p: np.ndarray, coeffs) -> np.ndarray:
    """Arctan-projected (..., 2) -> distorted normalised coordinates (..., 2) (steps 2-3 of the module docstring)."""
    return _distort_with_jacobian(p, coeffs, jacobian=False)[0]


def _distort_with_jacobian(p: np.ndarray, coeffs, jacobian: bool = True):
    k, (p1, p2), (s1, s2, s3, s4) = coeffs[:6], coeffs[6:8], coeffs[8:12]
    s = np.sum(p * p, axis=-1)
    radial, slope = _radial(s, k)
    u = p * radial[..., None]
    x, y = u[..., 0], u[..., 1]
    rho = x * x + y * y
    out = np.stack([x + 2 * p2 * x * y + p1 * (rho + 2 * x * x) + s1 * rho + s2 * rho * rho,
                    y + 2 * p1 * x * y + p2 * (rho + 2 * y * y) + s3 * rho + s4 * rho * rho], axis=-1)
    if not jacobian:
        return out, None
    # d u / d p = radial I + 2 radial'(s) p p^T; d out / d u from the tangential and thin-prism terms
    j1 = radial[..., None, None] * np.eye(2) + 2 * slope[..., None, None] * p[..., :, None] * p[..., None, :]
    a, b = s1 + 2 * s2 * rho, s3 + 2 * s4 * rho
    j2 = np.stack([np.stack([1 + 2 * p2 * y + 6 * p1 * x + 2 * a * x, 2 * p2 * x + 2 * p1 * y + 2 * a * y], -1),
                   np.stack([2 * p1 * y + 2 * p2 * x + 2 * b * x, 1 + 2 * p1 * x + 6 * p2 * y + 2 * b * y], -1)], -2)
    return out, j2 @ j1


@lru_cache(maxsize=64)
def radial_table(k: tuple) -> tuple[np.ndarray, np.ndarray]:
    """The radial map theta -> theta (1 + k1 theta^2 + ...) tabulated from 0 up to where it stops increasing (or
    pi): (theta, radius), both increasing. Its end is the model's field of view (:meth:`Fisheye624.max_angle`)."""
    theta = np.linspace(0.0, np.pi, 8193)
    radius = theta * _radial(theta * theta, k)[0]
    falls = np.flatnonzero(np.diff(radius) <= 0)
    end = falls[0] + 1 if falls.size else theta.size
    return theta[:end], radius[:end]


def undistort(q: np.ndarray, coeffs, iterations: int = 30) -> np.ndarray:
    """Distorted normalised (..., 2) -> arctan-projected (..., 2): Newton's method from p = q on the analytic
    Jacobian, each step halved (up to 20 times) while it does not reduce the residual, so that strongly distorted
    rims converge instead of overshooting."""
    q = np.asarray(q, np.float64)
    theta, radius = radial_table(tuple(float(c) for c in coeffs[:6]))
    r = np.linalg.norm(q, axis=-1, keepdims=True)
    p = q * np.interp(r, radius, theta) / np.maximum(r, 1e-300)  # the radial part inverted: on the right branch
    value, jac = _distort_with_jacobian(p, coeffs)
    for _ in range(iterations):
        residual = np.linalg.norm(value - q, axis=-1)
        if np.max(residual, initial=0.0) < 1e-14:
            break
        step = np.linalg.solve(jac, (value - q)[..., None])[..., 0]
        scale = np.ones(residual.shape)
        for _ in range(20):
            trial = p - scale[..., None] * step
            worse = np.linalg.norm(distort(trial, coeffs) - q, axis=-1) > residual
            if not np.any(worse):
                break
            scale = np.where(worse, scale / 2, scale)
        p = p - scale[..., None] * step
        value, jac = _distort_with_jacobian(p, coeffs)
    return p
