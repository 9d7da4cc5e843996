"""Starting points of a conversion for the models with distortion on a plane (Mei, OpenCV, FOV,
Fisheye624), from the source's focal lengths, principal point and radial profile."""

from __future__ import annotations

import math

import numpy as np

INITIAL_FROM_PROFILE = ("mei", "opencv", "fov", "fisheye624")
"""The models `initial_vector` starts."""


def initial_vector(model: str, fx: float, fy: float, cx: float, cy: float, theta: np.ndarray,
                   radius: np.ndarray) -> list[float]:
    """A parameter vector (`PARAMETER_NAMES` order) of ``model`` that has the source's focal lengths
    ``fx, fy`` at the optical axis and principal point, and fits its radial profile ``radius``
    (pixels from ``cx`` along +x) at the incidence angles ``theta`` (radians): ξ (mei) and ω (fov)
    by a grid search, k0..k5 (fisheye624) and k1..k6 (opencv, in front of the camera) by linear least
    squares; other coefficients 0."""
    rd = radius / fx  # focal units
    if model == "mei":  # r = sin θ / (cos θ + ξ), scaled by γ = f (1 + ξ) to keep the focal length at the axis
        best, xi = math.inf, 1.0
        for cand in np.linspace(0.0, 3.0, 61):
            den = np.cos(theta) + cand
            ok = den > 1e-6
            if theta.size and ok.mean() < 0.5:
                continue
            err = np.sum((np.sin(theta[ok]) / den[ok] * (1 + cand) - rd[ok]) ** 2) + 1e3 * np.sum(~ok)
            if err < best:
                best, xi = err, float(cand)
        return [fx * (1 + xi), fy * (1 + xi), cx, cy, xi, 0.0, 0.0, 0.0, 0.0]
    if model == "opencv":
        return [fx, fy, cx, cy, *_opencv_radial(theta, rd)]
    if model == "fov":
        best, w = math.inf, 1.0
        for cand in np.linspace(0.05, 3.1, 62):
            pred = np.arctan2(2 * math.tan(cand / 2) * np.sin(theta), np.cos(theta)) / cand
            err = float(np.sum((pred - rd) ** 2))
            if err < best:
                best, w = err, float(cand)
        return [fx, fy, cx, cy, w]
    if model == "fisheye624":
        k = [0.0] * 6
        if theta.size >= 12:
            k = list(np.linalg.lstsq(np.stack([theta ** (2 * i + 3) for i in range(6)], -1), rd - theta, rcond=None)[0])
        return [fx, fy, cx, cy, *k, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    raise ValueError(f"initial_vector: no starting point for model {model!r}")


def _opencv_radial(theta: np.ndarray, rd: np.ndarray) -> list[float]:
    """OpenCV's 12 coefficients with the rational radial part fitted to ``rd(theta)`` (linear least
    squares of ``rd (1 + k4 s + k5 s² + k6 s³) = r (1 + k1 s + k2 s² + k3 s³)``, ``r = tan theta``,
    ``s = r²``, on the rays in front below 85 degrees); the polynomial part alone when the rational
    fit's denominator is not positive there; zeros with fewer than 8 rays."""
    front = theta < math.radians(85.0)
    r, d = np.tan(theta[front]), rd[front]
    zeros = [0.0] * 12
    if r.size < 8:
        return zeros
    s = r * r
    rational = np.stack([r * s, r * s**2, r * s**3, -d * s, -d * s**2, -d * s**3], -1)
    k = np.linalg.lstsq(rational, d - r, rcond=None)[0]
    if np.all(1 + s * (k[3] + s * (k[4] + s * k[5])) > 0.1):
        return [k[0], k[1], 0.0, 0.0, k[2], k[3], k[4], k[5], 0.0, 0.0, 0.0, 0.0]
    k = np.linalg.lstsq(rational[:, :3], d - r, rcond=None)[0]
    return [k[0], k[1], 0.0, 0.0, k[2]] + [0.0] * 7
