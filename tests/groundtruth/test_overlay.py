"""Box wireframes and points drawn into fisheye images (`jaxfish.groundtruth.box_edge_pixels`,
`project_points` and the rasterisers): the drawn pixels unproject to rays that hit the box edges,
edges are split where the lens has no image, never joined across."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.groundtruth import (
    BOX_EDGES,
    CORNER_SIGNS,
    box_edge_pixels,
    draw_points,
    draw_polylines,
    draw_rectangles,
    project_points,
)
from tests.conftest import shared_path
from tests.tolerances import OVERLAY_DRAWN_PX, OVERLAY_SAMPLE_RAY_RAD


def _box(centre, half, yaw=0.0) -> np.ndarray:
    """Corners (8, 3) of a box in the vehicle frame (CORNER_SIGNS order), yawed about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (CORNER_SIGNS * np.asarray(half)) @ rot.T + np.asarray(centre)


def _boxes_around(calib) -> np.ndarray:
    """Boxes around the camera's mount: ahead, beside and partly out of the image, at 1.5-15 m."""
    t = np.asarray(calib.camera_to_vehicle.translation)
    axis = np.asarray(calib.camera_to_vehicle.rotation_matrix)[:, 2] * np.array([1.0, 1.0, 0.0])
    fwd = axis / np.linalg.norm(axis)
    side = np.array([-fwd[1], fwd[0], 0.0])
    ground = np.array([t[0], t[1], 0.0])
    return np.stack([
        _box(ground + 6 * fwd + [0, 0, 0.8], (2.2, 0.9, 0.8), 0.3),
        _box(ground + 3 * fwd + 3 * side + [0, 0, 0.9], (0.3, 0.3, 0.9)),
        _box(ground + 1.5 * fwd - 4 * side + [0, 0, 0.8], (2.0, 0.9, 0.8), 1.2),
        _box(ground + 15 * fwd + [0, 0, 1.5], (1.0, 1.0, 1.5)),
    ])


def _calibration(which: str):
    return jf.load_calibration(shared_path(f"calibration/{which}.json"), dtype=jnp.float64)


def _closest_edge_points(rays: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """For each ray (unit, from the origin) the point of each segment nearest to it: (R, E, 3)."""
    u = end - start  # (E, 3)
    d = rays[:, None, :]
    a = np.sum(u * u, -1)
    b = np.sum(u * d, -1)
    da = np.sum(d * start, -1)
    ua = np.sum(u * start, -1)
    t = np.clip((b * da - ua) / np.maximum(a - b * b, 1e-300), 0.0, 1.0)
    return start + t[..., None] * u


@pytest.mark.parametrize("which", ["synwoodscape/FV", "woodscape/FV"])
def test_drawn_edge_pixels_unproject_to_rays_that_hit_the_box_edges(which):
    """Every sample's pixel unprojects to the sample's own ray, and every pixel the rasteriser sets
    unprojects to a ray passing a box edge within one pixel, measured at the edge: the 3D edge
    point nearest to the ray projects within `OVERLAY_DRAWN_PX` of the pixel."""
    calib = _calibration(which)
    cam, pose = calib.camera, calib.vehicle_to_camera
    corners = _boxes_around(calib)
    edges = box_edge_pixels(cam, pose, corners, 96)
    uv, valid, drawn = np.asarray(edges.uv), np.asarray(edges.valid), np.asarray(edges.drawn)
    assert uv.shape == (4, 12, 96, 2) and drawn.shape == (4, 12, 95)
    assert valid.all() and drawn.mean() > 0.99  # these boxes lie inside the lens domain
    # Samples: exact (float64) rays.
    t = np.linspace(0.0, 1.0, 96)[:, None]
    pts = corners[:, BOX_EDGES[:, 0], None, :] * (1 - t) + corners[:, BOX_EDGES[:, 1], None, :] * t
    pts_cam = np.asarray(pose.apply(pts))
    rays, ok = cam.unproject(uv)
    r = np.asarray(rays)
    angle = np.arctan2(np.linalg.norm(np.cross(r, pts_cam), axis=-1), np.sum(r * pts_cam, -1))
    assert np.asarray(ok).all()
    assert angle.max() < OVERLAY_SAMPLE_RAY_RAD
    # Drawn pixels: within one pixel of an edge.
    image = draw_polylines(np.zeros((cam.height, cam.width, 3), np.uint8), uv, drawn, (255, 255, 255))
    err, pix = _edge_error_px(cam, pose, corners, image)
    assert len(err) > 2000
    assert err.max() < OVERLAY_DRAWN_PX, (err.max(), pix[np.argmax(err)])


def _edge_error_px(cam, pose, corners, image) -> tuple[np.ndarray, np.ndarray]:
    """For every set pixel of ``image``: unproject it, find the point of the boxes' edges nearest to
    its ray and return how far (pixels) that point projects from the pixel (inf where either has
    no ray / no image), with the pixels."""
    vv, uu = np.nonzero(image[..., 0])
    pix = np.stack([uu, vv], -1).astype(np.float64)
    n = len(pix)
    padded = np.concatenate([pix, np.repeat(pix[:1], -n % 4096, axis=0)])  # few shapes: compiled once
    rays, ok = cam.unproject(padded)
    rays, ok = np.asarray(rays)[:n], np.asarray(ok)[:n]
    cam_corners = np.asarray(pose.apply(corners))
    start = cam_corners[:, BOX_EDGES[:, 0]].reshape(-1, 3)
    end = cam_corners[:, BOX_EDGES[:, 1]].reshape(-1, 3)
    near = _closest_edge_points(rays, start, end)  # (R, E, 3)
    dist = np.linalg.norm(np.cross(near, rays[:, None, :]), axis=-1)  # distance to the ray, at the edge
    best = near[np.arange(len(pix)), np.argmin(dist / np.linalg.norm(near, axis=-1), axis=1)]
    back, ok_back = cam.project(np.concatenate([best, np.repeat(best[:1], -n % 4096, axis=0)]))
    err = np.linalg.norm(np.asarray(back)[:n] - pix, axis=-1)
    return np.where(ok & np.asarray(ok_back)[:n], err, np.inf), pix


def _wide_lens():
    """A WoodScape lens whose image radius stops increasing at about 89 degrees (k4 < 0): its domain
    boundary, a circle of ~350 px, lies inside the 1280 x 966 image."""
    return jf.WoodScapeFisheye(np.array([300.0, 0.0, 0.0, -20.0]), width=1280, height=966, dtype=jnp.float64)


def test_an_edge_leaving_the_lens_domain_is_split_there_never_drawn_across():
    cam = _wide_lens()
    theta_max = float(cam.theta_max())
    assert 1.5 < theta_max < 1.6
    rho_max = float(cam.rho_max())
    # Camera frame = vehicle frame here (identity pose); the box straddles the plane z = 0 beside the
    # camera: its edges along z run from theta 63 to 117 degrees, across the domain boundary.
    corners = (CORNER_SIGNS * np.array([0.5, 0.5, 1.0]) + np.array([2.5, 0.0, 0.0]))[None]
    edges = box_edge_pixels(cam, jf.Pose.identity(dtype=jnp.float64), corners, 64)
    valid, drawn, uv = np.asarray(edges.valid), np.asarray(edges.drawn), np.asarray(edges.uv)
    crossing = valid.any(-1) & ~valid.all(-1)
    assert crossing.sum() == 4  # the four edges along z
    # Chords only between valid samples, and each crossing edge is cut where it leaves the domain.
    assert not (drawn & ~(valid[..., 1:] & valid[..., :-1])).any()
    assert (drawn[crossing].sum(-1) < 63).all() and (drawn[crossing].sum(-1) > 10).all()
    image = draw_polylines(np.zeros((966, 1280, 3), np.uint8), uv, drawn, (255, 255, 255))
    vv, uu = np.nonzero(image[..., 0])
    cx, cy = np.asarray(cam.principal_point)
    assert len(uu) > 100
    assert np.hypot(uu - cx, vv - cy).max() <= rho_max + 1.0  # nothing beyond the domain's circle
    pose = jf.Pose.identity(dtype=jnp.float64)
    err, pix = _edge_error_px(cam, pose, corners, image)
    inside = np.hypot(pix[:, 0] - cx, pix[:, 1] - cy) <= rho_max  # a pixel centre rounded beyond has no ray
    assert inside.mean() > 0.95 and err[inside].max() < OVERLAY_DRAWN_PX
    # What "drawn across" would be: joining every consecutive sample draws the projection beyond the
    # domain (the radius folds back there), pixels whose rays miss the box.
    naive = draw_polylines(np.zeros((966, 1280, 3), np.uint8), uv, np.ones_like(drawn), (255, 255, 255))
    assert _edge_error_px(cam, pose, corners, naive)[0].max() > 10 * OVERLAY_DRAWN_PX


def test_an_edge_passing_the_back_axis_is_split_where_its_image_jumps():
    """A real 190-degree lens has an image of every direction but the back axis, where the azimuth
    flips: an edge passing 1 mm from it jumps across the image. The chord over the jump is not drawn
    (it would cut through the whole image); the rest of the edge is (outside the image)."""
    calib = _calibration("synwoodscape/FV")
    cam = calib.camera
    local = CORNER_SIGNS * np.array([1.0, 0.5, 0.5]) + np.array([0.0, 0.501, -5.5])  # camera frame, behind
    corners = np.asarray(calib.camera_to_vehicle.apply(local))[None]
    edges = box_edge_pixels(cam, calib.vehicle_to_camera, corners, 64)
    valid, drawn, uv = np.asarray(edges.valid), np.asarray(edges.drawn), np.asarray(edges.uv)
    assert valid.all()
    # Split only on the two edges along x at y = 1 mm from the axis (corner bit iy = 0), where the image
    # sweeps half the circle rho(pi) within a few samples; every other edge is drawn whole.
    near_axis = (BOX_EDGES[:, 1] - BOX_EDGES[:, 0] == 4) & (BOX_EDGES[:, 0] & 2 == 0)
    assert near_axis.sum() == 2
    assert (~drawn[0, near_axis]).any(-1).all() and drawn[0, ~near_axis].all()
    image = draw_polylines(np.zeros((cam.height, cam.width, 3), np.uint8), uv, drawn, (255, 255, 255))
    assert not image.any()  # the box is behind the camera: nothing of it is in the image
    naive = draw_polylines(np.zeros((cam.height, cam.width, 3), np.uint8), uv, np.ones_like(drawn), (255, 255, 255))
    assert naive.any()  # joining across the jump would draw a line through the image


def test_box_edge_pixels_under_jit_and_vmap():
    cam = _wide_lens()
    poses = jf.Pose(np.stack([np.eye(3)] * 3), np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.2, -0.5]]), dtype=jnp.float64)
    corners = np.stack([CORNER_SIGNS * 0.5 + [0.0, 0.0, 3.0], CORNER_SIGNS * 0.3 + [1.0, 0.0, 2.0]])
    eager = [box_edge_pixels(cam, jax.tree_util.tree_map(lambda a, i=i: a[i], poses), corners, 8) for i in range(3)]
    batched = jax.jit(jax.vmap(lambda p: box_edge_pixels(cam, p, corners, 8)))(poses)
    for i, e in enumerate(eager):
        np.testing.assert_allclose(np.asarray(batched.uv[i]), np.asarray(e.uv), rtol=0, atol=1e-9)
        assert (np.asarray(batched.drawn[i]) == np.asarray(e.drawn)).all()
    with pytest.raises(ValueError, match="corners_vehicle"):
        box_edge_pixels(cam, poses, np.zeros((2, 4, 3)))
    with pytest.raises(ValueError, match="samples_per_edge"):
        box_edge_pixels(cam, poses, corners, 1)


def test_points_are_drawn_at_their_projected_pixels():
    """Lidar-like points in the vehicle frame, placed on the rays of chosen pixels at chosen ranges:
    `project_points` gives those pixels and ranges back, and `draw_points` colours exactly them."""
    calib = _calibration("synwoodscape/FV")
    cam = calib.camera
    pix = np.array([[100.0, 200.0], [640.0, 483.0], [1100.0, 700.0], [300.0, 900.0]])
    rng = np.array([3.0, 12.5, 40.0, 1.5])
    rays, ok = cam.unproject(pix)
    pts = np.asarray(calib.camera_to_vehicle.apply(np.asarray(rays) * rng[:, None]))
    far = np.asarray(calib.camera_to_vehicle.apply(np.array([[0.0, 0.0, -10.0]])))  # on the back axis
    p = project_points(cam, calib.vehicle_to_camera, np.concatenate([pts, far]))
    valid = np.asarray(p.valid)
    assert valid.tolist() == [True, True, True, True, False]
    np.testing.assert_allclose(np.asarray(p.uv)[:4], pix, atol=1e-6)
    np.testing.assert_allclose(np.asarray(p.range_m)[:4], rng, rtol=1e-9)
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [9, 9, 9]], np.uint8)
    image = draw_points(np.zeros((cam.height, cam.width, 3), np.uint8), np.asarray(p.uv), valid, colors,
                        order=np.asarray(p.range_m))
    vv, uu = np.nonzero(image.any(-1))
    assert sorted(zip(uu.tolist(), vv.tolist(), strict=True)) == sorted(map(tuple, pix.astype(int).tolist()))
    assert (image[pix[:, 1].astype(int), pix[:, 0].astype(int)] == colors[:4]).all()
    # Nearer points cover farther ones on the same pixel, whatever their order in the input.
    two = draw_points(np.zeros((4, 4, 3), np.uint8), np.array([[1.0, 1.0], [1.2, 0.9]]), np.array([True, True]),
                      np.array([[10, 10, 10], [20, 20, 20]], np.uint8), order=np.array([1.0, 5.0]))
    assert two[1, 1].tolist() == [10, 10, 10]
    odd = draw_points(np.zeros((4, 4, 3), np.uint8), np.array([[np.nan, 1.0], [1e30, 1.0], [2.0, 2.0]]), np.ones(3, bool),
                      np.full((3, 3), 5, np.uint8))
    assert np.argwhere(odd[..., 0]).tolist() == [[2, 2]]  # non-finite or absurd pixels are skipped


def test_rectangles_and_clipping():
    image = draw_rectangles(np.zeros((10, 12, 3), np.uint8), np.array([[2, 3, 6, 7], [9, 8, 20, 30]]), (1, 2, 3))
    on = image[..., 0] == 1
    assert on[3, 2:7].all() and on[7, 2:7].all() and on[3:8, 2].all() and on[3:8, 6].all()
    assert not on[4:7, 3:6].any()  # outline only
    assert on[8, 9:12].all() and on[8:10, 9].all()  # clipped to the image
    # A polyline far outside the image draws nothing; one crossing it is clipped, not wrapped.
    uv = np.array([[[-1e6, 5.0], [1e6, 5.0]], [[-50.0, -50.0], [-40.0, -60.0]]])
    lines = draw_polylines(np.zeros((10, 12, 3), np.uint8), uv, np.ones((2, 1), bool), (7, 7, 7))
    assert (lines[5, :, 0] == 7).all() and lines[..., 0].sum() == 7 * 12
    # Ends far away are clipped exactly; at 1e30 pixels (rounding beyond a pixel) or not finite, a chord is
    # clipped to its row or skipped: never a huge allocation or a crash.
    uv = np.array([[[-1e12, 2.0], [1e12, 2.0]], [[np.nan, 1.0], [3.0, 1.0]], [[np.inf, 0.0], [-np.inf, 0.0]],
                   [[-1e30, 6.0], [1e30, 6.0]]])
    lines = draw_polylines(np.zeros((10, 12, 3), np.uint8), uv, np.ones((4, 1), bool), (7, 7, 7))
    assert (lines[2, :, 0] == 7).all() and lines[[0, 1, 3, 4, 5, 7, 8, 9], :, 0].sum() == 0
