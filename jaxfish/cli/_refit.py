"""``jaxfish refit`` and ``jaxfish convert``: fit intrinsics to correspondences, convert lens models."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import typer

from ._app import app, check_outputs, fail, print_warning, say


def _model_option(model: str | None) -> str | None:
    """``--model``/``--to`` as a canonical lens model name, or a clear error naming the option."""
    from ..refit import canonical_model_name

    if model is None:
        return None
    try:
        return canonical_model_name(model)
    except ValueError as e:
        raise fail(f"--model/--to {model!r}: {e}") from None


def _write_outputs(calibration, out: Path, report: Path | None, summary: dict[str, Any] | None) -> None:
    """The calibration and the report: both or neither. Both texts are made first: a calibration
    with a non-finite parameter, or one jaxfish's own loader refuses (a zero focal length, ...), and
    a report holding a non-finite number write nothing (exit status 1: the inputs were read, the
    result is unusable); a report that cannot be written removes the calibration just written."""
    import numpy as np

    from .._errors import JaxfishError
    from ..io import atomic_write_text, camera_calibration_from_dict, camera_calibration_to_dict
    from ..io._json import to_json_text
    from ..refit import intrinsics_vector

    nothing = "" if report is None else f"; {report} not written either"
    values = np.asarray(intrinsics_vector(calibration.camera))
    if not np.all(np.isfinite(values)):
        raise fail(f"--out {out}: not written, the fitted parameters are not finite ({values.tolist()}){nothing}", code=1)
    try:
        text = to_json_text(out, camera_calibration_to_dict(calibration), indent=2)
        camera_calibration_from_dict(json.loads(text), source=str(out))  # what reading it back would say
    except ValueError as e:
        raise fail(f"{out}: not written, jaxfish could not read it back: {e}{nothing}", code=1) from None
    try:
        report_text = None if report is None else to_json_text(report, summary, indent=2)
    except JaxfishError as e:
        raise fail(f"{e}; {out} not written either", code=1) from None
    existed = out.exists()
    atomic_write_text(out, text)
    if report is None or report_text is None:
        return
    try:
        atomic_write_text(report, report_text)
    except OSError as e:
        if not existed:
            out.unlink(missing_ok=True)
        raise fail(f"--report {report}: {e.strerror or e}; {out} not written either") from None


def _pose_dict(pose) -> dict[str, list[float]]:
    import numpy as np

    return {"quaternion": [float(x) for x in np.asarray(pose.as_quaternion_xyzw())],
            "translation": [float(x) for x in np.asarray(pose.translation)]}


def _initial_camera(model: str, width: int, height: int, focal: float | None):
    import numpy as np

    from ..refit import PARAMETER_NAMES, camera_from_intrinsics, canonical_model_name

    model = canonical_model_name(model)
    f = focal if focal is not None else width / math.pi  # equidistant lens spanning 180 degrees
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    vec = {
        "radial_poly": [f, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        "kannala_brandt": [f, f, cx, cy, 0.0, 0.0, 0.0, 0.0],
        "unified": [f, f, cx, cy, 0.5],
        "extended_unified": [f, f, cx, cy, 0.5, 1.0],
        "double_sphere": [f, f, cx, cy, 0.0, 0.5],
        "pinhole": [f, f, cx, cy],
        "mei": [2 * f, 2 * f, cx, cy, 1.0, 0.0, 0.0, 0.0, 0.0],
        "opencv": [f, f, cx, cy] + [0.0] * 12,
        "fov": [f, f, cx, cy, 1.0],
        "fisheye624": [f, f, cx, cy] + [0.0] * 12,
        "ocamcalib": [cy, cx, 1.0, 0.0, 0.0, -f] + [0.0] * (len(PARAMETER_NAMES["ocamcalib"]) - 6),
        "ftheta": [cx, cy, 1.0 / f] + [0.0] * 9 + [math.pi, 1.0, 0.0, 0.0],
        "carla_wide_angle": [2 * math.degrees(height / (2 * f)), 0.0, 0.0, 0.0, 0.0],
    }[model]
    return camera_from_intrinsics(model, np.asarray(vec), width=width, height=height, dtype=np.float64)


EXAMPLE_VIEWS = 5
"""Board views in the `example_correspondences` file."""


def example_correspondences():
    """``(correspondences, calibration)``: the corners of a 20 x 20 checkerboard (6 cm squares) in
    `EXAMPLE_VIEWS` views 0.35-0.6 m from the default rig's FV camera (1280 x 966, 190 degrees), some
    beyond 70 degrees off-axis, projected with that camera and 0.2 px of Gaussian noise (seed 0);
    corners off the image have weight 0. ``jaxfish refit --example OUT`` writes them."""
    import jax.numpy as jnp
    import numpy as np

    from .. import default_rig
    from ..refit import Correspondences, rotation_from_vector
    from ..transforms import Pose

    calib = default_rig(dtype=jnp.float64)["FV"]
    cam = calib.camera
    g = np.stack(np.meshgrid(np.arange(20), np.arange(20)), -1).reshape(-1, 2) * 0.06
    board = np.c_[g - g.mean(axis=0), np.zeros(len(g))]
    omegas = np.array([[0.1, -0.2, 0.05], [0.5, 0.3, -0.2], [-0.4, 0.6, 0.3], [0.2, -0.7, 0.1], [-0.6, -0.3, -0.4]])
    ts = np.array([[0.0, 0.0, 0.6], [-0.5, 0.1, 0.45], [0.6, -0.3, 0.5], [0.2, 0.5, 0.35], [-0.3, -0.4, 0.55]])
    poses = Pose(rotation_from_vector(jnp.asarray(omegas)), jnp.asarray(ts))
    pts = np.tile(board, (EXAMPLE_VIEWS, 1))
    view = np.repeat(np.arange(EXAMPLE_VIEWS), len(board))
    pc = jnp.einsum("nij,nj->ni", poses.rotation_matrix[view], jnp.asarray(pts)) + poses.translation[view]
    uv, valid = cam.project(pc)
    valid = np.asarray(valid & cam.contains(uv))
    pixels = np.where(valid[:, None], np.asarray(uv), 0.0) + np.random.default_rng(0).normal(size=(len(pts), 2)) * 0.2
    return Correspondences(pts, pixels, view, valid.astype(np.float64), dtype=np.float64), calib


def _write_example(path: Path | None) -> None:
    """``--example OUT``: write `example_correspondences` and exit (eager: no other option needed)."""
    if path is None:
        return
    check_outputs(example=path)
    import jax

    jax.config.update("jax_enable_x64", True)
    from ..io import save_correspondences

    corr, _ = example_correspondences()
    save_correspondences(corr, path, frame="board", view_names=[f"img_{i:03d}" for i in range(EXAMPLE_VIEWS)])
    say(f"wrote {path}: {int(corr.weight.sum())} checkerboard corners in {EXAMPLE_VIEWS} views of a 1280x966 "
        "fisheye (jaxfish's default FV camera, 0.2 px noise); fit it with: jaxfish refit "
        f"{path} --model radial_poly --width 1280 --height 966 --out fitted.json")
    raise typer.Exit(0)


def _degenerate(path: Path, corr, result) -> str:
    """Why a refit has no covariance: how many distinct correspondences there are for how many
    free parameters."""
    import numpy as np

    used = np.asarray(corr.weight) > 0
    rows = np.c_[np.asarray(corr.view)[used], np.asarray(corr.points)[used], np.asarray(corr.pixels)[used]]
    distinct = len(np.unique(rows, axis=0))
    return (f"{path}: degenerate correspondences: {int(used.sum())} points ({distinct} distinct) do not determine "
            f"the {len(result.parameter_names)} free parameters (covariance and standard deviations not estimable; "
            "give more distinct points, or --fix parameters); nothing written")


@app.command()
def refit(
    correspondences: Path = typer.Argument(..., help="Correspondences JSON (format: docs/refit.md; "
                                           "--example writes one)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output calibration JSON."),
    calibration: Path | None = typer.Option(None, "--calibration", "-c", help="Initial calibration JSON (any model): "
                                            "the default of --model, the image size, the start values of every "
                                            "parameter, the extrinsic, the name and the file flavor."),
    model: str | None = typer.Option(None, "--model", "-m", help="Lens model to fit (default: the --calibration's; "
                                     "a different one is converted first). Required without --calibration."),
    width: int | None = typer.Option(None, help="Image width, 1 to 65536 pixels (without --calibration; required then)."),
    height: int | None = typer.Option(None, help="Image height, 1 to 65536 pixels (without --calibration; required then)."),
    focal: float | None = typer.Option(None, help="Initial focal length, pixels per radian (without --calibration; "
                                       "default: width / pi, an equidistant lens spanning 180 degrees)."),
    name: str = typer.Option("camera", help="Camera name written without --calibration (with it: its name)."),
    fix: list[str] = typer.Option([], "--fix", help="Parameter to hold fixed (repeatable), e.g. --fix k4."),
    loss: str = typer.Option("linear", help="Robust loss: linear, huber, cauchy, soft_l1."),
    loss_scale: float = typer.Option(1.0, help="Robust loss scale in pixels."),
    fit_pose: bool = typer.Option(True, "--fit-pose/--no-fit-pose", help="Also fit the pose(s)."),
    report: Path | None = typer.Option(None, "--report", "-r", help="Report JSON (residuals, covariance, poses)."),
    example: Path | None = typer.Option(None, "--example", is_eager=True, callback=_write_example,
                                        help="Write an example correspondences file to this path and exit."),
    rig: list[Path] = typer.Option([], "--rig", help="Rig mode: the rig's initial calibration files (repeatable; "
                                   "any format jaxfish reads, a kalibr camchain gives every camera). The "
                                   "correspondences name a camera per view; --out is a folder (NAME.json per camera)."),
    reference: str | None = typer.Option(None, "--reference", help="Rig mode: the camera whose mounting is held "
                                         "(the gauge; default: the first camera, none with frame vehicle)."),
    estimate_mountings: bool = typer.Option(False, "--estimate-mountings", help="Rig mode: start every other "
                                            "camera's mounting from the target views it shares with placed cameras "
                                            "(kalibr's initialisation) instead of the --rig files' extrinsics."),
) -> None:
    """Fit a lens model's intrinsics (and poses) to 2D-3D correspondences; write the calibration and a report.

    With --calibration, the model, image size, start values, extrinsic, name and flavor come from
    that file; without it, give --model, --width and --height (and optionally --focal, --name).
    With --rig, every camera's intrinsics and mounting and the target poses are fitted jointly.
    """
    if rig or reference is not None or estimate_mountings:
        from ._refit_rig import refit_rig_command

        others = {"--calibration": calibration is not None, "--model": model is not None, "--width": width is not None,
                  "--height": height is not None, "--focal": focal is not None}
        refit_rig_command(correspondences, rig, out, report, reference, fix, loss, loss_scale, fit_pose,
                          [k for k, v in others.items() if v], estimate_mountings)
        return
    check_outputs(out=out, report=report)
    model = _model_option(model)
    if not (math.isfinite(loss_scale) and loss_scale > 0):
        raise fail(f"--loss-scale must be a positive finite number of pixels, got {loss_scale}")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from ..calibration import Calibration
    from ..io import load_camera_calibration, load_correspondences
    from ..refit import Correspondences, canonical_model_name, convert_camera
    from ..refit import refit as run_refit
    from ..transforms import Pose

    corr, frame, view_names = load_correspondences(correspondences)
    flavor = "woodscape"
    if calibration is not None:
        calib = load_camera_calibration(calibration, dtype=np.float64)
        camera, mount = calib.camera, calib.camera_to_vehicle
        name, flavor = calib.name, calib.flavor
        if model is not None and model != canonical_model_name(camera):
            try:
                camera = convert_camera(camera, model).camera
            except ValueError as e:
                raise fail(f"{calibration}: {e}") from None
    else:
        if model is None or width is None or height is None:
            raise fail("without --calibration, give --model, --width and --height")
        from ..cameras import MAX_IMAGE_SIDE

        for option, size in (("--width", width), ("--height", height)):
            if not 0 < size <= MAX_IMAGE_SIDE:  # the initial camera's image size
                raise fail(f"{option} must be positive and at most {MAX_IMAGE_SIDE} pixels, got {size}")
        if focal is not None and not (math.isfinite(focal) and focal > 0):
            raise fail(f"--focal must be a positive number of pixels per radian, got {focal}")
        camera = _initial_camera(model, width, height, focal)
        mount = Pose.identity(dtype=np.float64)
    poses = None
    pose_fitted = fit_pose and frame != "camera"
    if frame == "vehicle":  # one mounting pose shared by every view
        corr = Correspondences(corr.points, corr.pixels, None, corr.weight, dtype=np.float64)
        if calibration is not None:
            poses = mount.inverse()
    try:
        result = run_refit(camera, corr, poses=poses, fit_pose=pose_fitted, fixed=fix, loss=loss,
                           loss_scale_px=loss_scale)
    except ValueError as e:
        raise fail(f"{correspondences}: {e}") from None
    if frame == "vehicle" and pose_fitted:
        mount = Pose(result.poses.rotation_matrix[0], result.poses.translation[0]).inverse()
    names = view_names if frame != "vehicle" else ["vehicle"]
    std = dict(zip(result.parameter_names, np.asarray(result.standard_deviations).tolist(), strict=True))
    pnames = [n for n in result.parameter_names if not n.startswith("view")]
    from ..refit import intrinsics_vector, parameter_names

    values = dict(zip(parameter_names(result.camera), np.asarray(intrinsics_vector(result.camera)).tolist(),
                      strict=True))
    summary = {
        "model": canonical_model_name(result.camera),
        "frame": frame,
        "num_correspondences": int(np.sum(np.asarray(corr.weight) > 0)),
        "rms_px": float(result.rms_px),
        "per_view_rms_px": dict(zip(names, np.asarray(result.per_view_rms_px).tolist(), strict=True)),
        "num_steps": int(result.num_steps),
        "converged": bool(result.converged),
        "loss": loss, "loss_scale_px": loss_scale,
        "parameters": {k: {"value": v, "std": std.get(k), "fixed": k not in std} for k, v in values.items()},
    }
    if not result.determined:
        raise fail(_degenerate(correspondences, corr, result), code=1)
    say(
        f"refit {summary['model']}: rms {summary['rms_px']:.4f} px over {summary['num_correspondences']} points, "
        f"{summary['num_steps']} steps, converged={summary['converged']}")
    for k in pnames:
        say(f"  {k} = {values[k]:.6g} ± {std[k]:.2g}")
    full = None
    if report is not None:
        view = np.asarray(corr.view)
        res = np.asarray(result.residuals)
        full = dict(summary)
        full["poses_world_to_camera"] = {
            n: _pose_dict(Pose(result.poses.rotation_matrix[i], result.poses.translation[i]))
            for i, n in enumerate(names)}
        full["residuals_px"] = {n: res[view == i].tolist() for i, n in enumerate(names)}
        full["covariance"] = {"names": list(result.parameter_names),
                              "matrix": np.asarray(result.covariance).tolist()}
    _write_outputs(Calibration(name, result.camera, mount, flavor), out, report, full)
    say(f"wrote {out}")
    if not bool(result.converged):
        print_warning(f"the solver did not converge in {summary['num_steps']} steps; {out} holds its last iterate")
        raise typer.Exit(1)


DEFAULT_MAX_ERROR_PX = 2.0
"""`jaxfish convert` writes nothing when the maximum error over the fitted domain exceeds this
(pixels), unless ``--force``."""


@app.command()
def convert(
    calibration: Path = typer.Argument(..., help="Calibration JSON of any lens model."),
    to: str = typer.Option(..., "--to", "-t", help="Target model: radial_poly (woodscape), kannala_brandt (kb), "
                           "unified (ucm), extended_unified (eucm), double_sphere (ds), mei, opencv, fov, "
                           "fisheye624, ocamcalib, ftheta, carla_wide_angle (jaxfish.refit.MODEL_CLASSES)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output calibration JSON."),
    fov: str = typer.Option("image", help="Fit over the image's valid pixels ('image', default) or the source's "
                            "whole lens ('lens')."),
    theta_max_deg: float | None = typer.Option(None, help="Fit over rays up to this incidence angle instead (degrees)."),
    max_error: float = typer.Option(DEFAULT_MAX_ERROR_PX, "--max-error", help="Largest acceptable error over the "
                                    "fitted domain (pixels): beyond it nothing is written (exit status 2)."),
    force: bool = typer.Option(False, "--force", help="Write the files even when the error exceeds --max-error "
                               "or rays of the domain lie outside the target's."),
    report: Path | None = typer.Option(None, "--report", "-r", help="Error report JSON."),
) -> None:
    """Convert a calibration to another lens model, reporting the fitted domain and the max and RMS
    reprojection difference over it; nothing is written when the error exceeds --max-error."""
    check_outputs(out=out, report=report)
    target = _model_option(to)
    if fov not in ("image", "lens"):
        raise fail(f"--fov must be 'image' or 'lens', got {fov!r}")
    if theta_max_deg is not None and not (math.isfinite(theta_max_deg) and theta_max_deg > 0):
        raise fail(f"--theta-max-deg must be a positive finite number of degrees, got {theta_max_deg}")
    if not (math.isfinite(max_error) and max_error > 0):
        raise fail(f"--max-error must be a positive finite number of pixels, got {max_error}")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from ..calibration import Calibration
    from ..io import load_camera_calibration
    from ..refit import canonical_model_name, convert_camera

    calib = load_camera_calibration(calibration, dtype=np.float64)
    try:
        result = convert_camera(calib.camera, target, fov=fov,
                                theta_max=None if theta_max_deg is None else math.radians(theta_max_deg))
    except ValueError as e:
        raise fail(f"{calibration}: {e}") from None
    cam = calib.camera
    if theta_max_deg is not None:
        domain_kind = f"rays up to {theta_max_deg:g} deg"
    elif fov == "image":
        domain_kind = f"the {cam.width}x{cam.height} image's valid pixels"
    else:
        domain_kind = "the source's whole lens"
    theta_deg = math.degrees(float(result.theta_max))
    radius = float(result.max_radius_px)
    domain = f"{domain_kind} (up to {theta_deg:.1f} deg off-axis, {radius:.0f} px from the principal point)"
    summary = {
        "source_model": canonical_model_name(cam), "target_model": target,
        "domain": {"kind": "theta_max" if theta_max_deg is not None else fov, "theta_max_deg": theta_deg,
                   "max_radius_px": radius, "image_width": cam.width, "image_height": cam.height,
                   "description": domain},
        "max_px": float(result.max_px), "rms_px": float(result.rms_px),
        "max_px_in_image": float(result.max_px_in_image), "rms_px_in_image": float(result.rms_px_in_image),
        "max_error_px": max_error, "forced": force,
        "theta_max_deg": theta_deg, "num_samples": int(result.num_samples),
        "num_target_invalid": int(result.num_target_invalid), "num_steps": int(result.num_steps),
        "num_starts": int(result.num_starts), "converged": bool(result.converged),
    }
    say(
        f"{summary['source_model']} -> {target} over {domain}: max {summary['max_px']:.4g} px, "
        f"rms {summary['rms_px']:.4g} px (inside the image: max {summary['max_px_in_image']:.4g}, "
        f"rms {summary['rms_px_in_image']:.4g}); {summary['num_target_invalid']} of {summary['num_samples']} rays "
        f"outside the target's domain")
    problems = []
    if summary["max_px"] > max_error:
        problems.append(f"maximum error {summary['max_px']:.4g} px exceeds --max-error {max_error:g} px")
    if summary["num_target_invalid"] > 0:
        problems.append(f"{summary['num_target_invalid']} of {summary['num_samples']} rays lie outside the "
                        f"{target} model's domain")
    if problems and not force:
        raise fail(f"{calibration}: converting to {target} over {domain}: {'; '.join(problems)}; {out} not written"
                   f"{'' if report is None else f' (nor {report})'} (--force writes it anyway; --theta-max-deg "
                   "narrows the domain)")
    _write_outputs(Calibration(calib.name, result.camera, calib.camera_to_vehicle, calib.flavor), out, report, summary)
    if problems:
        print_warning(f"{'; '.join(problems)}; written anyway (--force)")
    say(f"wrote {out}")
