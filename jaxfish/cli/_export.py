"""``jaxfish export``: write calibrations in the formats of other tools (kalibr, COLMAP, OpenCV,
basalt, CARLA), converting a lens model the format lacks first."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import typer

from ._app import app, check_outputs, fail, print_warning, say

DEFAULT_TARGETS = ("kannala_brandt", "carla_wide_angle", "mei", "opencv", "double_sphere", "pinhole")
"""The model a camera is converted to when the format lacks its own and ``--to`` is not given:
the first of these the format holds (Kannala-Brandt: every fisheye tool has it, and it follows
wide-angle lenses within about a pixel)."""


@app.command()
def export(
    calibrations: list[Path] = typer.Argument(..., help="Calibration files (any format jaxfish reads; a file of "
                                              "several cameras gives them all, PATH::NAME one), COLMAP folders or "
                                              "folders of calibration JSON files."),
    fmt: str = typer.Option(..., "--format", "-f", help="kalibr, colmap, opencv, basalt or carla."),
    out: Path = typer.Option(..., "--out", "-o", help="Output file (kalibr YAML, basalt JSON, CARLA JSON, OpenCV YAML "
                             "of one camera) or folder (COLMAP text model; OpenCV NAME.yaml per camera)."),
    to: str | None = typer.Option(None, "--to", "-t", help="Model to convert cameras to when the format lacks "
                                  "theirs (default: kannala_brandt, or what the format holds)."),
    max_error: float = typer.Option(2.0, "--max-error", help="Largest conversion error allowed over the image's "
                                    "field of view, pixels: above it nothing is written (exit 1) unless --force."),
    force: bool = typer.Option(False, "--force", help="Write even when a conversion exceeds --max-error."),
    report: Path | None = typer.Option(None, "--report", "-r", help="Report JSON (per camera: model, conversion "
                                       "error)."),
) -> None:
    """Export calibrations to another tool's format. A camera whose model the format holds is written
    exactly; another is converted first (over the image's field of view, as ``jaxfish convert``
    does) and its error reported."""
    from ..io._formats import EXPORT_FORMATS

    if fmt not in EXPORT_FORMATS:
        raise fail(f"--format {fmt!r}: expected one of {', '.join(EXPORT_FORMATS)}")
    if not (math.isfinite(max_error) and max_error > 0):
        raise fail(f"--max-error must be a positive number of pixels, got {max_error}")
    check_outputs(out=out, report=report, directories=("out",))
    folder_out = fmt == "colmap"
    if not folder_out and fmt != "opencv" and out.is_dir():
        raise fail(f"--out {out}: is a directory, expected a file path ({fmt} writes one file)")
    if folder_out and out.exists() and not out.is_dir():
        raise fail(f"--out {out}: exists and is not a folder (COLMAP's text model is a folder)")
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from ..calibration import Calibration
    from ..io._formats import (
        check_export_names,
        export_calibrations,
        format_free_parameters,
        format_models,
        holds_exactly,
        read_calibration_paths,
    )
    from ..refit import canonical_model_name, convert_camera, intrinsics_vector, parameter_names

    models = format_models(fmt)
    target = None
    if to is not None:
        try:
            target = canonical_model_name(to)
        except ValueError as e:
            raise fail(f"--to {to!r}: {e}") from None
        if target not in models:
            raise fail(f"--to {target}: {fmt} does not hold that model (it holds: {', '.join(models) or 'none'})")
    calibs = read_calibration_paths(calibrations, dtype=np.float64)
    names = [c.name for c in calibs]
    check_export_names(names, fmt, out)
    written: list[Calibration] = []
    rows = []
    refused = []
    for c in calibs:
        source_model = canonical_model_name(c.camera)
        row: dict = {"name": c.name, "source_model": source_model}
        if holds_exactly(fmt, c) and (target is None or target == source_model):
            row.update(model=source_model, converted=False, max_px=0.0, rms_px=0.0)
            written.append(c)
            rows.append(row)
            say(f"{c.name}: {source_model}, written exactly")
            continue
        goal = target or next((m for m in DEFAULT_TARGETS if m in models), None)
        if goal is None:
            raise fail(f"{c.name}: {fmt} cannot hold a {source_model} camera, and holds no model to convert it to")
        free = format_free_parameters(fmt, goal) or ()
        fixed = [n for n in parameter_names(goal) if n not in free]
        try:
            res = convert_camera(c.camera, goal, fov="image", fixed=fixed or None)
        except ValueError as e:
            raise fail(f"{c.name}: converting {source_model} -> {goal}: {e}") from None
        converted = Calibration(c.name, res.camera, c.camera_to_vehicle, c.flavor)
        max_px, rms_px = float(res.max_px), float(res.rms_px)
        theta_deg = math.degrees(float(res.theta_max))
        radius = getattr(res, "max_radius_px", None)
        domain = (f"the {c.camera.width}x{c.camera.height} image's valid pixels (up to {theta_deg:.1f} deg off-axis"
                  + (f", {float(radius):.0f} px from the principal point)" if radius is not None else ")"))
        invalid, samples = int(res.num_target_invalid), int(res.num_samples)
        row.update(model=goal, converted=True, max_px=max_px, rms_px=rms_px, domain=domain, theta_max_deg=theta_deg,
                   num_samples=samples, num_target_invalid=invalid, converged=bool(res.converged))
        if radius is not None:
            row["max_radius_px"] = float(radius)
        rows.append(row)
        say(f"{c.name}: {source_model} -> {goal} over {domain}: max {max_px:.4g} px, rms {rms_px:.4g} px; "
            f"{invalid} of {samples} rays outside the target's domain")
        if not np.all(np.isfinite(np.asarray(intrinsics_vector(res.camera)))):
            raise fail(f"{c.name}: converting {source_model} -> {goal} gave non-finite parameters; nothing written", code=1)
        if not holds_exactly(fmt, converted):
            raise fail(f"{c.name}: the converted {goal} camera is not one {fmt} holds exactly; nothing written", code=1)
        problems = []
        if not max_px <= max_error:
            problems.append(f"maximum error {max_px:.4g} px exceeds --max-error {max_error:g} px")
        if invalid > 0:
            problems.append(f"{invalid} of {samples} rays lie outside the {goal} model's domain")
        if problems:
            refused.append(f"{c.name} -> {goal} over {domain}: {'; '.join(problems)}")
        written.append(converted)
    if refused and not force:
        raise fail(f"{' | '.join(refused)}; nothing written (--force writes anyway; --to picks another model)")
    if refused:
        print_warning(f"{' | '.join(refused)}; written anyway (--force)")
    from ..io import atomic_write_text
    from ..io._json import to_json_text

    report_text = None if report is None else to_json_text(report, {"format": fmt, "cameras": rows}, indent=2)
    existed = out.exists()
    before = set(out.iterdir()) if out.is_dir() else ({out} if existed else set())
    try:
        paths = export_calibrations(written, fmt, out)
    except ValueError as e:
        raise fail(str(e), code=1) from None
    if report is not None and report_text is not None:
        try:
            atomic_write_text(report, report_text)
        except OSError as e:  # both or neither: the files this run made go again
            for p in paths:
                if Path(p) not in before:
                    Path(p).unlink(missing_ok=True)
            if folder_out and not existed:
                with contextlib.suppress(OSError):
                    out.rmdir()  # only when empty
            raise fail(f"--report {report}: {e.strerror or e}; {out} not written either") from None
    for p in paths:
        say(f"wrote {p}")

