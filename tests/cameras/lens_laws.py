"""Laws every lens model keeps, written once for the model test files (test_mei, test_opencv_pinhole,
test_fov, test_fisheye624): pixel -> ray -> pixel on the image, ray -> pixel -> ray up to the
domain's edge, just beyond it invalid, and implicit gradients equal to finite differences."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfish.refit import intrinsics_vector, with_intrinsics
from tests import tolerances as tol
from tests.helpers import central_difference_jacobian, three_ways


def rays_up_to(theta_max: float, n: int, seed: int = 0) -> np.ndarray:
    """``n`` unit rays with incidence angles uniform in ``[0, theta_max]`` and random azimuths."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, theta_max, n)
    phi = rng.uniform(0.0, 2 * math.pi, n)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)


def image_grid(cam, n: int = 24, dtype=jnp.float64) -> jnp.ndarray:
    """An ``n x n`` lattice of pixels spanning the whole image, borders included."""
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, n), np.linspace(-0.5, cam.height - 0.5, n))
    return jnp.asarray(np.stack([u, v], -1).reshape(-1, 2), dtype)


def _roundtrip(c, x):
    rays, valid = c.unproject(x)
    back, bvalid = c.project(rays)
    return rays, back, valid & bvalid, valid


_jit_roundtrip = jax.jit(_roundtrip)  # one compile per model, image size and dtype for the session


def check_pixel_ray_pixel(cam, *, atol: float, min_valid: float = 1.0, dtype=jnp.float64,
                          three: bool = False) -> None:
    """Every image pixel the model gives a ray projects back onto itself; at least ``min_valid``
    of the image has rays. ``three``: eager, jitted and vmapped (`three_ways`, three compiles),
    else jitted once per model."""
    cam = cam.astype(dtype)
    grid = image_grid(cam, dtype=dtype)
    results = three_ways(_roundtrip, cam, grid) if three else [jax.tree_util.tree_map(np.asarray, _jit_roundtrip(cam, grid))]
    for rays, back, both, valid in results:
        assert rays.dtype == dtype and np.isfinite(rays).all() and np.isfinite(back).all()
        assert valid.mean() >= min_valid, valid.mean()
        np.testing.assert_array_equal(both, valid)  # a valid ray projects validly
        np.testing.assert_allclose(back[valid], np.asarray(grid)[valid], rtol=0, atol=atol)
        np.testing.assert_allclose(np.linalg.norm(rays[valid], axis=-1), 1.0, atol=10 * np.finfo(dtype).eps)


def check_ray_pixel_ray_to_the_edge(cam, jit_project, jit_unproject, *, theta_top: float | None = None,
                                    n: int = 512) -> None:
    """Rays up to ``theta_max`` (or ``theta_top``) are valid and come back from their pixels (float64);
    rays just beyond ``theta_max`` are invalid."""
    tm = float(cam.theta_max())
    top = tm - 1e-6 if theta_top is None else theta_top
    rays = rays_up_to(top, n)
    rays[-1] = [math.sin(top), 0.0, math.cos(top)]  # the edge itself
    uv, valid = jit_project(cam, jnp.asarray(rays))
    assert bool(jnp.all(valid))
    back, bvalid = jit_unproject(cam, uv)
    assert bool(jnp.all(bvalid))
    again, _ = jit_project(cam, back)
    np.testing.assert_allclose(np.asarray(again), np.asarray(uv), rtol=1e-13, atol=tol.MODEL_PX_F64 * 10)  # rtol: pixels 1e7 px out
    if tm < math.pi - 1e-3:
        over = np.array([[math.sin(tm + 1e-4), 0.0, math.cos(tm + 1e-4)], [0.0, math.sin(tm + 1e-3), math.cos(tm + 1e-3)]])
        assert not np.asarray(jit_project(cam, jnp.asarray(over))[1]).any()


def check_gradients(cam, uv: np.ndarray, *, eps: float = 1e-6) -> None:
    """d(rays)/d(intrinsics) of `unproject` (implicit gradients) and d(pixels)/d(intrinsics) of
    `project`: jacfwd = jacrev, and both equal central differences; finite everywhere."""
    p0 = np.asarray(intrinsics_vector(cam))
    uv = jnp.asarray(uv)
    rays, valid = cam.unproject(uv)
    assert bool(jnp.all(valid))
    points = rays * 2.0

    def unproject(v):
        return with_intrinsics(cam, v).unproject(uv)[0].reshape(-1)

    def project(v):
        return with_intrinsics(cam, v).project(points)[0].reshape(-1)

    for fn in (jax.jit(unproject), jax.jit(project)):  # compiled once: 2 x n_params evaluations follow
        fwd = np.asarray(jax.jit(jax.jacfwd(fn))(jnp.asarray(p0)))
        rev = np.asarray(jax.jit(jax.jacrev(fn))(jnp.asarray(p0)))
        assert np.isfinite(fwd).all()
        np.testing.assert_allclose(fwd, rev, rtol=0, atol=tol.JAC_FWD_REV * max(1.0, np.abs(fwd).max()))
        steps = eps * np.maximum(np.abs(p0), 1e-2)
        num = np.stack([(np.asarray(fn(jnp.asarray(p0 + np.eye(len(p0))[i] * steps[i])))
                         - np.asarray(fn(jnp.asarray(p0 - np.eye(len(p0))[i] * steps[i])))) / (2 * steps[i])
                        for i in range(len(p0))], -1)
        np.testing.assert_allclose(fwd, num, rtol=tol.JAC_FINITE_DIFF_REL, atol=tol.JAC_FINITE_DIFF_REL * np.abs(num).max())
    # With respect to the pixels too.
    jac_uv = np.asarray(jax.jacfwd(lambda x: cam.unproject(x)[0])(uv[0]))
    num_uv = central_difference_jacobian(lambda x: np.asarray(cam.unproject(jnp.asarray(x))[0]), np.asarray(uv[0]), 1e-4)
    np.testing.assert_allclose(jac_uv, num_uv, rtol=1e-6, atol=1e-9)


def check_batch_of_cameras(cam_a, cam_b) -> None:
    """A batch of two cameras (stacked leaves) under ``jit(vmap)``: the same rays as each camera
    alone, and a finite gradient of the masked rays with respect to both cameras' parameters."""
    cams = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), cam_a, cam_b)
    grid = image_grid(cam_a, n=8)
    rays, valid = jax.jit(jax.vmap(lambda c, x: c.unproject(x), in_axes=(0, None)))(cams, grid)
    for i, cam in enumerate((cam_a, cam_b)):
        alone, valid_alone = cam.unproject(grid)
        np.testing.assert_array_equal(np.asarray(valid[i]), np.asarray(valid_alone))
        np.testing.assert_allclose(np.asarray(rays[i]), np.asarray(alone), rtol=0, atol=1e-12)

    def loss(c):
        r, v = jax.vmap(lambda cc: cc.unproject(grid))(c)
        return jnp.sum(jnp.where(v[..., None], r, 0.0))

    grads = jax.grad(loss)(cams)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree_util.tree_leaves(grads))
