"""Surface detail (``textured`` scenes): deterministic, off by default, consistent between cameras
and instants, and far richer in PNG terms than the smooth materials (small renders only; the ±30 %
match to the real frame is `scripts/bench_build.py`'s check at full size)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfish.io import encode_png
from jaxfish.scene import (
    CaptureConfig,
    cast_rays,
    generate_street,
    render_cube_faces,
    sky_detail,
    surface_detail,
    to_uint8,
)

from .conftest import FACE


def up_bits_per_pixel(rgb: np.ndarray) -> float:
    """Bits per pixel of an RGB image as jaxfish writes it (`jaxfish.io.encode_png`: the "Up" row
    filter, one deflate stream at level 1)."""
    return 8.0 * len(encode_png(np.ascontiguousarray(rgb, np.uint8), png_level=1)) / (rgb.shape[0] * rgb.shape[1])


@pytest.fixture(scope="module")
def textured(small_rig):
    """Frame 0 of seed 0 with surface detail."""
    return generate_street(0, rig=small_rig, textured=True)


@pytest.fixture(scope="module")
def fv_textured(textured, small_rig):
    return render_cube_faces(textured, small_rig["FV"], FACE, time=1.0)


def test_texture_is_off_by_default(street, small_rig, faces_t):
    assert CaptureConfig().textured is False
    assert street.scene.textured is False
    explicit = render_cube_faces(generate_street(0, rig=small_rig, textured=False), small_rig["FV"], FACE, time=1.0)
    for name, buf in faces_t["FV"].items():
        np.testing.assert_array_equal(np.asarray(explicit[name].rgb), np.asarray(buf.rgb))
    with pytest.raises(ValueError, match="textured"):
        CaptureConfig(textured="yes")


def test_textured_renders_are_deterministic(textured, small_rig, fv_textured):
    again = render_cube_faces(generate_street(0, rig=small_rig, textured=True), small_rig["FV"], FACE, time=1.0)
    for name, buf in fv_textured.items():
        np.testing.assert_array_equal(np.asarray(again[name].rgb), np.asarray(buf.rgb))
    other_seed = render_cube_faces(generate_street(1, rig=small_rig, textured=True), small_rig["FV"], FACE, time=1.0)
    assert not np.array_equal(np.asarray(other_seed["front"].rgb), np.asarray(fv_textured["front"].rgb))


def test_texture_changes_only_the_colours(faces_t, fv_textured):
    for name, buf in fv_textured.items():
        smooth = faces_t["FV"][name]
        for field in ("valid", "hit", "depth_m", "semantic", "actor_id", "object_index", "point_world"):
            np.testing.assert_array_equal(np.asarray(getattr(buf, field)), np.asarray(getattr(smooth, field)), err_msg=field)
        assert not np.array_equal(np.asarray(buf.rgb), np.asarray(smooth.rgb))


def test_textured_faces_compress_far_worse_than_smooth_ones(faces_t, fv_textured):
    smooth = np.concatenate([to_uint8(faces_t["FV"][n].rgb) for n in fv_textured])
    rich = np.concatenate([to_uint8(b.rgb) for b in fv_textured.values()])
    smooth_bpp, rich_bpp = up_bits_per_pixel(smooth), up_bits_per_pixel(rich)
    # loose bounds (48 px faces: the smooth ones are mostly edges, about 6 bits/px; textured about 17)
    assert rich_bpp > 2.0 * smooth_bpp and rich_bpp > smooth_bpp + 6.0, (smooth_bpp, rich_bpp)


def test_a_moving_surface_point_keeps_its_colour(textured):
    """The detail moves with its object: a point of a car at t-1, seen again where the car took it
    at t (same sun angle for a car driving straight), has the same colour."""
    scene = textured.scene
    car = next(a for a in textured.actors[1:] if a.category == "four_wheeler" and a.displacement_m > 0.1
               and abs(a.rotation[1] - a.rotation_prev[1]) < 1e-9)
    origin = np.asarray(textured.ego.location) + np.array([0.0, 0.0, 1.5])
    rng = np.random.default_rng(0)
    centre = np.asarray(car.bbox_corners("t-1")).mean(axis=0)
    targets = centre + rng.uniform(-0.4, 0.4, (64, 3)) * np.asarray(car.bbox_extent)
    d0 = targets - origin
    d0 /= np.linalg.norm(d0, axis=-1, keepdims=True)
    o = jnp.asarray(np.broadcast_to(origin, d0.shape), jnp.float32)
    b0 = cast_rays(scene, o, jnp.asarray(d0, jnp.float32), time=0.0)
    on_car = np.asarray(b0.actor_id) == car.id
    assert on_car.sum() >= 16
    p1 = np.asarray(scene.move_points(b0.object_index, b0.point_world, 0.0, 1.0), np.float64)
    d1 = p1 - origin
    d1 /= np.linalg.norm(d1, axis=-1, keepdims=True)
    b1 = cast_rays(scene, o, jnp.asarray(d1, jnp.float32), time=1.0)
    seen = on_car & (np.asarray(b1.actor_id) == car.id)
    seen &= np.linalg.norm(np.asarray(b1.point_world) - p1, axis=-1) < 1e-4  # not occluded at t
    assert seen.sum() >= 16
    same = np.all(np.abs(np.asarray(b1.rgb) - np.asarray(b0.rgb)) < 1e-5, axis=-1)
    assert same[seen].mean() >= 0.9, same[seen].mean()  # a grain cell's edge may fall between the two points


def test_detail_is_a_pure_function_of_point_material_and_salt():
    rng = np.random.default_rng(3)
    uv = jnp.asarray(rng.uniform(-50, 50, (256, 2)), jnp.float32)
    tag = jnp.asarray(rng.integers(0, 23, 256), jnp.int32)
    salt = jnp.asarray(rng.integers(0, 2**32, 256, dtype=np.uint64).astype(np.uint32))
    a = np.asarray(surface_detail(uv, tag, salt))
    np.testing.assert_array_equal(a, np.asarray(surface_detail(uv, tag, salt)))
    assert a.shape == (256, 3) and np.all(np.isfinite(a)) and np.all(a >= 0)
    assert not np.array_equal(a, np.asarray(surface_detail(uv, tag, salt + jnp.uint32(1))))
    d = jnp.asarray(rng.normal(size=(256, 3)), jnp.float32)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    s = np.asarray(sky_detail(d, jnp.uint32(7)))
    np.testing.assert_array_equal(s, np.asarray(sky_detail(d, jnp.uint32(7))))
    assert s.shape == (256, 3) and np.all(np.isfinite(s)) and np.all(s >= 0)


class _Stop(Exception):
    pass


def test_the_option_reaches_the_scene_from_the_cli_the_capture_writer_and_the_embedded_source(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import jaxfish as jf
    import jaxfish.dataset as dataset
    import jaxfish.dataset._synthesize as synthesize
    import jaxfish.scene as scene
    from jaxfish.cli import app

    seen = []

    def fake_synthesize(out, rig, *, frames, seed, config, progress, shard=None):
        seen.append(config.textured)

    monkeypatch.setattr(dataset, "synthesize_capture", fake_synthesize)
    monkeypatch.setattr("jaxfish.cli._synth.warn_undersampled", lambda *args: None)  # compiles: not tested here
    rig = {"RV": jf.default_rig()["RV"].resize(64, 48).astype(jnp.float32)}
    jf.save_rig(rig, tmp_path / "rig")
    for flag in ([], ["--texture"]):
        result = CliRunner().invoke(app, ["synth", "--out", str(tmp_path / "cli"), "--face-size", "32",
                                          "--rig", str(tmp_path / "rig"), *flag])
        assert result.exit_code == 0, result.output
    assert seen == [False, True]

    def fake_street(*args, textured=False, **kwargs):
        seen.append(textured)
        raise _Stop

    monkeypatch.setattr(synthesize, "generate_street", fake_street)
    monkeypatch.setattr(scene, "generate_street", fake_street)
    for textured in (False, True):
        config = CaptureConfig(face_size=16, textured=textured)
        with pytest.raises(_Stop):
            synthesize._synthesize_locked(tmp_path / f"cap{textured}", rig, [0], 0, config, scene.sensor_mounts(rig, config), None)
        with pytest.raises(_Stop):
            dataset.EmbeddedSource(rig, frames=1, config=config).read(0)
    assert seen[2:] == [False, False, True, True]
    smooth, rich = (dataset.EmbeddedSource(rig, frames=1, config=CaptureConfig(textured=t)).fingerprint() for t in (False, True))
    assert smooth["embedded"] != rich["embedded"]
