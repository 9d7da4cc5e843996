"""``jaxfish refit --rig``: the joint refit of a camera rig (`jaxfish.refit.refit_rig`)."""

from __future__ import annotations

import math
from pathlib import Path

import typer

from ._app import fail, print_warning, say


def refit_rig_command(correspondences: Path, rig_files: list[Path], out: Path, report: Path | None,
                      reference: str | None, fix: list[str], loss: str, loss_scale: float, fit_pose: bool,
                      single_options: list[str], estimate_mountings: bool = False) -> None:
    """Read the rig and its correspondences, fit, and write ``out/NAME.json`` per camera (jaxfish's
    calibration JSON) and the report: all of them or nothing."""
    if not rig_files:
        raise fail("--reference and --estimate-mountings need --rig (the rig's calibration files)")
    if single_options:
        raise fail(f"{', '.join(single_options)}: not used with --rig (the models, sizes and start values come from "
                   "the --rig files)")
    if out.exists() and not out.is_dir():
        raise fail(f"--out {out}: exists and is not a folder (with --rig, --out is the folder of NAME.json files)")
    if report is not None and report.is_dir():
        raise fail(f"--report {report}: is a directory, expected a file path")
    if not (math.isfinite(loss_scale) and loss_scale > 0):
        raise fail(f"--loss-scale must be a positive finite number of pixels, got {loss_scale}")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from ..io import (
        atomic_write_text,
        camera_calibration_from_dict,
        camera_calibration_to_dict,
        load_rig_correspondences,
    )
    from ..io._formats import read_calibration_paths
    from ..io._formats._common import file_stem
    from ..io._json import to_json_text
    from ..refit import canonical_model_name, intrinsics_vector, parameter_names, refit_rig
    from ..transforms import Pose

    calibs = read_calibration_paths(rig_files, dtype=np.float64)
    names = [c.name for c in calibs]
    for n in names:
        file_stem(n, f"--out {out}")
    data = load_rig_correspondences(correspondences)
    unknown = [c for c in data.observations if c not in names]
    if unknown:
        raise fail(f"{correspondences}: views name camera {unknown[0]!r}, which the --rig files lack "
                   f"(cameras: {', '.join(names)})")
    vehicle = data.frame == "vehicle"
    if reference is not None and reference not in names:
        raise fail(f"--reference {reference!r}: not a camera of the rig (cameras: {', '.join(names)})")
    ref = reference if reference is not None else (None if vehicle else 0)
    n_targets = len(data.target_names)
    targets = None
    if vehicle:
        eye = np.broadcast_to(np.eye(3), (n_targets, 3, 3))
        targets = Pose(eye, np.zeros((n_targets, 3)), dtype=np.float64)
    try:
        result = refit_rig(calibs, data.observations, target_poses=targets, fit_targets=fit_pose and not vehicle,
                           reference=ref, estimate_mountings=estimate_mountings and ref is not None, fixed=fix, target_names=data.target_names, loss=loss,
                           loss_scale_px=loss_scale)
    except ValueError as e:
        raise fail(f"{correspondences}: {e}") from None
    if not result.determined:
        raise fail(f"{correspondences}: the correspondences do not determine the {len(result.parameter_names)} free "
                   "parameters (cameras seeing too few targets, or targets seen by no second camera: covariance not "
                   "estimable; --fix parameters or add views); nothing written", code=1)
    std = dict(zip(result.parameter_names, np.asarray(result.standard_deviations).tolist(), strict=True))
    say(f"refit rig of {len(calibs)} cameras, {n_targets} target views: rms {float(result.rms_px):.4f} px, "
        f"{int(result.num_steps)} steps, converged={bool(result.converged)}")
    cameras = {}
    texts = {}
    for i, c in enumerate(result.calibrations):
        values = dict(zip(parameter_names(c.camera), np.asarray(intrinsics_vector(c.camera)).tolist(), strict=True))
        if not all(math.isfinite(v) for v in values.values()):
            raise fail(f"{c.name}: the fitted parameters are not finite; nothing written", code=1)
        q = np.asarray(c.camera_to_vehicle.as_quaternion_xyzw()).tolist()
        t = np.asarray(c.camera_to_vehicle.translation).tolist()
        cameras[c.name] = {
            "model": canonical_model_name(c.camera),
            "rms_px": float(result.per_camera_rms_px[i]),
            "num_correspondences": int(np.sum(np.asarray(result.valid[i]))),
            "intrinsics": {k: {"value": v, "std": std.get(f"{c.name}.{k}")} for k, v in values.items()},
            "camera_to_vehicle": {"quaternion": q, "translation": t,
                                  "std": {k: std.get(f"{c.name}.{k}") for k in ("rx", "ry", "rz", "tx", "ty", "tz")}},
        }
        say(f"  {c.name}: rms {cameras[c.name]['rms_px']:.4f} px over {cameras[c.name]['num_correspondences']} points")
        path = out / f"{c.name}.json"
        text = to_json_text(path, camera_calibration_to_dict(c), indent=2)
        try:
            import json

            camera_calibration_from_dict(json.loads(text), source=str(path))
        except ValueError as e:
            raise fail(f"{path}: not written, jaxfish could not read it back: {e}; nothing written", code=1) from None
        texts[path] = text
    summary = {
        "frame": data.frame, "reference": None if ref is None else names[ref] if isinstance(ref, int) else ref,
        "rms_px": float(result.rms_px), "num_steps": int(result.num_steps), "converged": bool(result.converged),
        "loss": loss, "loss_scale_px": loss_scale, "cameras": cameras,
        "target_poses_to_vehicle": {
            n: {"quaternion": np.asarray(Pose(result.target_poses.rotation_matrix[v],
                                              result.target_poses.translation[v]).as_quaternion_xyzw()).tolist(),
                "translation": np.asarray(result.target_poses.translation[v]).tolist()}
            for v, n in enumerate(result.target_names)},
        "covariance": {"names": list(result.parameter_names), "matrix": np.asarray(result.covariance).tolist()},
    }
    report_text = None if report is None else to_json_text(report, summary, indent=2)
    out.mkdir(parents=True, exist_ok=True)
    for path, text in texts.items():
        atomic_write_text(path, text)
        say(f"wrote {path}")
    if report is not None and report_text is not None:
        atomic_write_text(report, report_text)
        say(f"wrote {report}")
    if not bool(result.converged):
        print_warning(f"the solver did not converge in {int(result.num_steps)} steps; the files hold its last iterate")
        raise typer.Exit(1)
