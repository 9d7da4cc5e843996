"""The caster's geometry against closed forms, run eager / jit / vmap."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from jaxfish.io import decode_depth, encode_depth
from jaxfish.scene import FAR_M, cast_rays, ray_box_distance, ray_capsule_distance, ray_ground_distance
from tests.helpers import three_ways
from tests.tolerances import CARLA_DEPTH_QUANTUM_M, SCENE_CLOSED_FORM_M, SCENE_PLANAR_DEPTH_REL

F = np.float32


def _unit(v):
    v = np.asarray(v, np.float64)
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(F)


def test_ray_box_closed_form():
    h = np.array([[1.0, 2.0, 3.0]] * 4, F)
    o = np.array([[-10.0, 0.5, 0.5], [0.5, 7.0, -1.0], [-10.0, 5.0, 0.0], [0.0, 0.0, 0.0]], F)
    d = _unit([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    # entry at x = -1 (9 m), y = 2 (5 m), a miss, and a ray starting inside (not an entry: inf)
    expected = np.array([9.0, 5.0, np.inf, np.inf])
    for got in three_ways(lambda o, d, h: ray_box_distance(jnp.asarray(o), jnp.asarray(d), jnp.asarray(h)), o, d, h):
        np.testing.assert_allclose(got, expected, atol=SCENE_CLOSED_FORM_M)


def test_ray_box_oblique_hits_the_entered_face():
    h = np.array([1.0, 1.0, 1.0], F)
    o = np.array([-4.0, -3.0, 0.2], F)
    d = _unit([4.0, 3.0, 0.0])  # towards the centre: enters the x = -1 face at y = -0.75
    t = float(ray_box_distance(jnp.asarray(o), jnp.asarray(d), jnp.asarray(h)))
    np.testing.assert_allclose(t, 3.0 / 0.8, atol=SCENE_CLOSED_FORM_M)


def test_ray_capsule_closed_form():
    hl = np.full(5, 1.0, F)
    r = np.full(5, 0.5, F)
    o = np.array([[-5.0, 0.0, 0.0], [0.0, 0.0, 10.0], [-5.0, 0.0, 1.3], [-5.0, 0.0, 1.6], [0.3, 0.0, -8.0]], F)
    d = _unit([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    expected = np.array([
        4.5,  # side of the cylinder
        8.5,  # straight down onto the top sphere (a top view: parallel to the axis)
        5.0 - math.sqrt(0.25 - 0.09),  # the top sphere at height 0.3 above the segment end
        np.inf,  # above the capsule
        8.0 - 1.0 - math.sqrt(0.25 - 0.09),  # straight up into the bottom sphere, off-axis
    ])
    fn = lambda o, d, hl, r: ray_capsule_distance(jnp.asarray(o), jnp.asarray(d), jnp.asarray(hl), jnp.asarray(r))  # noqa: E731
    for got in three_ways(fn, o, d, hl, r):
        np.testing.assert_allclose(got, expected, atol=SCENE_CLOSED_FORM_M)


def test_thin_far_capsule_keeps_its_silhouette_in_float32():
    """A 5 cm pole 40 m away, rays swept across it: the float32 entry distances match the float64
    closed form within the closed-form tolerance, and hit exactly the same rays (the discriminant
    without its cancellation)."""
    r, hl, far = 0.05, 3.0, 40.0
    y = np.linspace(-0.06, 0.06, 2001)
    o = np.stack([np.full_like(y, -far), np.zeros_like(y), np.zeros_like(y)], axis=-1)
    d = np.stack([np.full_like(y, far), y, np.full_like(y, 0.3)], axis=-1)
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(F).astype(np.float64)  # the rays float32 casts
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
    disc = b * b - a * (o[:, 0] ** 2 + o[:, 1] ** 2 - r * r)
    t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)
    t = np.where(np.abs(o[:, 2] + t * d[:, 2]) <= hl, t, np.inf)
    fn = lambda o, d: ray_capsule_distance(jnp.asarray(o), jnp.asarray(d), jnp.float32(hl), jnp.float32(r))  # noqa: E731
    for got in three_ways(fn, o.astype(F), d.astype(F)):
        got = np.asarray(got, np.float64)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(t))
        hit = np.isfinite(t)
        assert 1000 < hit.sum() < y.size
        np.testing.assert_allclose(got[hit], t[hit], atol=SCENE_CLOSED_FORM_M)


def test_culling_tests_exactly_the_primitives_a_chunk_can_hit(street, small_rig):
    """Every chunk of a camera's faces, tested against the cull's survivors only and against every
    active primitive: the same nearest distance and primitive, bit for bit."""
    import jax

    from jaxfish.reprojection import CubeRig
    from jaxfish.scene._caster import _camera_rays, _candidates, _nearest, _pose_primitives, _tile_order
    from jaxfish.transforms import Pose

    scene, chunk, size = street.scene, 256, 128
    posed = _pose_primitives(scene, jnp.float32(1.0))
    radius = jnp.sqrt(jnp.sum(scene.box_half_extent**2, axis=-1))

    @jax.jit
    def culled_and_all(o, d):
        cb = _candidates(o, d, posed.box_center, radius, scene.box_active)
        ck = _candidates(o, d, posed.cap_center, scene.capsule_half_length + scene.capsule_radius, scene.capsule_active)
        culled = _nearest(scene, posed, o, d, jnp.argsort(~cb, stable=True), jnp.sum(cb),
                          jnp.argsort(~ck, stable=True), jnp.sum(ck))
        every = _nearest(scene, posed, o, d, jnp.argsort(~scene.box_active, stable=True), jnp.sum(scene.box_active),
                         jnp.argsort(~scene.capsule_active, stable=True), jnp.sum(scene.capsule_active))
        return culled, every, jnp.sum(cb) + jnp.sum(ck)

    rig = CubeRig(size, dtype=jnp.float32)
    calib = small_rig["FV"]
    mount = Pose(calib.camera_to_vehicle.rotation_matrix, calib.camera_to_vehicle.translation, dtype=jnp.float32)
    tested = hits = 0
    for face in rig.faces:
        o, d, _, _ = _camera_rays(rig.face, scene.camera_to_world(mount @ rig.face_pose(face), 1.0),
                                  rig.face.pixel_grid(jnp.float32))
        order, _ = _tile_order(size, size, chunk)
        o, d = np.asarray(o)[order].reshape(-1, chunk, 3), np.asarray(d)[order].reshape(-1, chunk, 3)
        for oc, dc in zip(o, d, strict=True):
            (t, idx), (t_all, idx_all), n = culled_and_all(oc, dc)
            np.testing.assert_array_equal(np.asarray(t), np.asarray(t_all))
            np.testing.assert_array_equal(np.asarray(idx), np.asarray(idx_all))
            tested += int(n)
            hits += int(np.sum(np.asarray(idx) > 0))
    n_all = int(jnp.sum(scene.box_active) + jnp.sum(scene.capsule_active))
    assert hits > 0 and tested < 0.2 * n_all * len(rig.faces) * (size * size // chunk)  # the cull drops most


def test_ray_ground_closed_form():
    o = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [3.0, 1.0, 50.0]], F)
    d = _unit([[1.0, 0.0, -1.0], [1.0, 0.0, 0.5], [0.0, 0.0, -1.0]])
    expected = np.array([2 * math.sqrt(2.0), np.inf, 50.0])
    for got in three_ways(lambda o, d: ray_ground_distance(jnp.asarray(o), jnp.asarray(d)), o, d):
        np.testing.assert_allclose(got, expected, rtol=1e-6)


def test_cast_rays_hits_the_ground_at_the_known_point(street):
    # straight down from 30 m above the road far ahead of everything: the road at (x, y, 0)
    o = np.array([[500.0, 0.5, 30.0], [500.0, 3.0, 30.0]], F)
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], F)
    b = cast_rays(street.scene, o, d)
    np.testing.assert_allclose(np.asarray(b.range_m), [30.0, 30.0], atol=SCENE_CLOSED_FORM_M)
    np.testing.assert_allclose(np.asarray(b.point_world)[:, 2], 0.0, atol=SCENE_CLOSED_FORM_M)
    np.testing.assert_array_equal(np.asarray(b.semantic), [7, 7])
    np.testing.assert_allclose(np.asarray(b.normal_world), [[0, 0, 1]] * 2)
    up = cast_rays(street.scene, o, -d)
    assert not np.any(np.asarray(up.hit)) and np.all(np.asarray(up.semantic) == 13)
    np.testing.assert_array_equal(np.asarray(up.range_m), FAR_M)


def test_planar_depth_is_range_times_cosine(faces_t):
    from jaxfish.reprojection import CubeRig

    face = CubeRig(48).face
    rays, _ = face.unproject(face.pixel_grid(jnp.float64))
    cos = np.asarray(rays[..., 2])
    for faces in faces_t.values():
        for b in faces.values():
            hit = np.asarray(b.hit)
            np.testing.assert_allclose(np.asarray(b.depth_m)[hit], (np.asarray(b.range_m) * cos)[hit],
                                       rtol=SCENE_PLANAR_DEPTH_REL)
            assert np.all(np.asarray(b.depth_m)[~hit] == FAR_M)


def test_encoded_depth_round_trip(faces_t):
    b = faces_t["FV"]["bottom"]
    depth = np.asarray(b.depth_m, np.float64)
    back = decode_depth(encode_depth(depth))
    # half a quantum, plus the float32 rounding of the decoded metres
    assert np.all(np.abs(back - depth) <= 0.5 * CARLA_DEPTH_QUANTUM_M + 1e-7 * depth)
    # the CARLA formula, written out: metres = 1000 (R + 256 G + 256² B) / (256³ - 1)
    bgra = encode_depth(depth).astype(np.float64)
    formula = 1000.0 * (bgra[..., 2] + 256 * bgra[..., 1] + 65536 * bgra[..., 0]) / (256**3 - 1)
    np.testing.assert_allclose(formula, back, atol=1e-6)


def test_buffers_are_finite_everywhere(faces_t):
    for faces in faces_t.values():
        for b in faces.values():
            for field in ("range_m", "depth_m", "rgb", "point_world", "normal_world"):
                assert np.all(np.isfinite(np.asarray(getattr(b, field)))), field
            rgb = np.asarray(b.rgb)
            assert rgb.min() >= 0.0 and rgb.max() <= 1.0


def test_any_camera_model_hit_points_project_back_to_their_pixels(street, small_rig, small_config):
    """Equirectangular (full sphere) and orthographic (BEV) renders: every hit point, taken back to
    the camera frame, projects to the pixel it was rendered at; up is sky in the panorama."""
    from jaxfish import Equirectangular
    from jaxfish.scene import bev_camera, render, sensor_mounts

    mounts = sensor_mounts(small_rig, small_config)
    pano = Equirectangular(width=64, height=32, dtype=jnp.float32)
    cases = [(pano, mounts.front_camera_to_vehicle), (bev_camera(small_config), mounts.bev_camera_to_vehicle)]
    for cam, mount in cases:
        pose = street.scene.camera_to_world(mount, 1.0)
        b = render(street.scene, cam, pose)
        hit = np.asarray(b.hit)
        assert np.all(np.asarray(b.valid)) and hit.sum() > 0.3 * hit.size
        p_cam = pose.inverse().apply(b.point_world)
        uv, ok = cam.project(p_cam)
        grid = np.asarray(cam.pixel_grid())
        assert np.all(np.asarray(ok)[hit])
        # beyond 1 m: float32 world coordinates blur the longitude of a point 5 cm below the pole
        far = hit & (np.asarray(b.range_m) > 1.0)
        np.testing.assert_allclose(np.asarray(uv)[far], grid[far], atol=2e-3)
    b = render(street.scene, pano, street.scene.camera_to_world(mounts.front_camera_to_vehicle, 1.0))
    assert np.all(np.asarray(b.semantic)[0] == 13)


def test_tile_order_is_a_permutation_by_tiles_with_its_inverse_kept():
    from jaxfish.scene._caster import _tile_order

    h, w, chunk = 13, 22, 16  # 4 x 4 tiles, partial ones at the right and bottom edges
    order, inverse = _tile_order(h, w, chunk)
    assert order.dtype == inverse.dtype == np.int32
    np.testing.assert_array_equal(np.sort(order), np.arange(h * w))
    np.testing.assert_array_equal(order[inverse], np.arange(h * w))
    np.testing.assert_array_equal(inverse, np.argsort(order))
    r, c = np.divmod(order, w)
    tile = (r // 4) * math.ceil(w / 4) + c // 4
    assert np.all(np.diff(tile) >= 0)  # tile after tile
    assert _tile_order(h, w, chunk)[0] is order and not order.flags.writeable  # one pair per size, kept


def test_colour_only_render_equals_the_full_render(street, small_rig):
    """`render_rgb` (the DVS sub-frames' render) gives `render`'s colours bit for bit, for a fisheye
    and for a cube face."""
    from jaxfish.reprojection import CubeRig
    from jaxfish.scene._caster import render, render_rgb

    calib = small_rig["FV"]
    rig = CubeRig(64, dtype=jnp.float32)
    for camera, mount in ((calib.camera, calib.camera_to_vehicle), (rig.face, calib.camera_to_vehicle @ rig.face_pose("left"))):
        for time in (0.25, 1.0):
            pose = street.scene.camera_to_world(mount, time)
            full = render(street.scene, camera, pose, time=time)
            rgb = np.asarray(render_rgb(street.scene, camera, pose, time=time))
            assert np.asarray(full.hit).any() and not np.asarray(full.hit).all()
            np.testing.assert_array_equal(rgb, np.asarray(full.rgb))


def test_cast_rays_of_no_ray_and_of_several_blocks(street):
    """No ray gives empty buffers; rays spanning several blocks (the last one partial) give the
    rays cast one block at a time."""
    from jaxfish.scene._caster import _cast_flat

    empty = cast_rays(street.scene, np.zeros((0, 3), F), np.zeros((0, 3), F))
    assert empty.range_m.shape == (0,) and empty.rgb.shape == (0, 3)
    rng = np.random.default_rng(0)
    o = np.tile(np.array([[0.0, 0.0, 1.6]], F), (700, 1)) + rng.normal(0, 0.1, (700, 3)).astype(F)
    d = _unit(rng.normal(0, 1, (700, 3)) + [1.0, 0.0, 0.0])
    whole = _cast_flat(street.scene, jnp.asarray(o), jnp.asarray(d), 1.0, 64, block_size=256)  # 3 blocks
    for start in (0, 256, 512):
        part = _cast_flat(street.scene, jnp.asarray(o[start:start + 256]), jnp.asarray(d[start:start + 256]), 1.0, 64,
                          block_size=256)
        for key, value in part.items():
            np.testing.assert_array_equal(np.asarray(whole[key])[start:start + 256], np.asarray(value), err_msg=key)
