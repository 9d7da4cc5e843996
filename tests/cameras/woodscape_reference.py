"""An independent float64 NumPy transcription of the WoodScape reference math
(valeoai/WoodScape ``scripts/calibration/projection.py``), used as the test oracle."""

from __future__ import annotations

import json

import numpy as np


def load_reference_intrinsics(path) -> dict:
    """k (4,), cx, cy (pixel-centre convention), aspect ratio, width, height — read straight from JSON."""
    with open(path) as f:
        intr = json.load(f)["intrinsic"]
    return dict(
        k=np.array([intr["k1"], intr["k2"], intr["k3"], intr["k4"]], dtype=np.float64),
        cx=intr["width"] / 2 + intr["cx_offset"] - 0.5,
        cy=intr["height"] / 2 + intr["cy_offset"] - 0.5,
        aspect=float(intr["aspect_ratio"]),
        width=int(intr["width"]),
        height=int(intr["height"]),
    )


def reference_project(points: np.ndarray, intr: dict) -> np.ndarray:
    """projection.py: chi, theta = atan2(chi, z), rho = poly(theta), u = rho x / chi + cx ..."""
    p = np.asarray(points, dtype=np.float64)
    chi = np.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
    theta = np.arctan2(chi, p[..., 2])
    k = intr["k"]
    rho = k[0] * theta + k[1] * theta**2 + k[2] * theta**3 + k[3] * theta**4
    with np.errstate(invalid="ignore", divide="ignore"):
        lx = np.where(chi > 0, p[..., 0] / chi, 0.0)
        ly = np.where(chi > 0, p[..., 1] / chi, 0.0)
    u = rho * lx + intr["cx"]
    v = rho * ly * intr["aspect"] + intr["cy"]
    return np.stack([u, v], axis=-1)


def reference_theta_np_roots(rho: float, k: np.ndarray) -> float:
    """The reference inversion: np.roots of k4 θ⁴ + k3 θ³ + k2 θ² + k1 θ - rho, smallest real root in [0, pi]."""
    roots = np.roots([k[3], k[2], k[1], k[0], -rho])
    real = roots[np.abs(roots.imag) < 1e-9].real
    real = real[(real >= -1e-12) & (real <= np.pi)]
    return float(np.min(real)) if real.size else np.nan


def reference_unproject(uv: np.ndarray, intr: dict) -> np.ndarray:
    """Pixel -> unit ray with the per-pixel np.roots inversion (slow: for a sample of pixels)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    out = np.empty((uv.shape[0], 3))
    for i, (u, v) in enumerate(uv):
        x = u - intr["cx"]
        y = (v - intr["cy"]) / intr["aspect"]
        rho = np.hypot(x, y)
        theta = reference_theta_np_roots(rho, intr["k"])
        if rho == 0:
            out[i] = (0.0, 0.0, 1.0)
        else:
            out[i] = (np.sin(theta) * x / rho, np.sin(theta) * y / rho, np.cos(theta))
    return out
