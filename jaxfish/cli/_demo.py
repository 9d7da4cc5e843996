"""``jaxfish demo OUT``: the README's one-command demo."""

from __future__ import annotations

from pathlib import Path

import typer

from ._app import app, console


@app.command()
def demo(
    out: Path = typer.Argument(..., help="Output directory (created)."),
    calibration: Path | None = typer.Option(None, "--calibration", "-c", help="Calibration directory (default: jaxfish's own rig)."),
) -> None:
    """Load a rig, report its geometry, and write per-camera incidence-angle maps and the rig JSONs."""
    import jax.numpy as jnp
    import numpy as np

    from .. import default_rig, load_rig, save_rig
    from ..io import write_image

    rig = load_rig(calibration) if calibration is not None else default_rig()
    out.mkdir(parents=True, exist_ok=True)
    save_rig(rig, out / "calibration")
    for name, calib in rig.items():
        cam = calib.camera
        rays, valid = cam.unproject(cam.pixel_grid(jnp.float32))
        theta = np.degrees(np.arccos(np.clip(np.asarray(rays[..., 2]), -1.0, 1.0)))
        theta = np.where(np.asarray(valid), theta, 0.0)
        img = np.clip(theta / 180.0 * 65535.0, 0, 65535).astype(np.uint16)
        write_image(out / f"theta_{name}.png", img)
        console.print(
            f"{name}: {cam.width}x{cam.height}, principal point {np.asarray(cam.principal_point).round(3)}, "
            f"field of view {2 * theta.max():.1f} deg, theta_max {np.degrees(float(cam.theta_max())):.1f} deg",
            highlight=False,
        )
    console.print(f"wrote {out}", highlight=False)
