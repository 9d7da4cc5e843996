"""`build_lut` refuses a ``target_to_source`` that is not a finite rotation, a non-floating dtype
and a supersample that is not an integer >= 1, eagerly (ValueError / TypeError) and under jit."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfish as jf
from jaxfish.reprojection import build_lut, compiled_build_lut, supersample_offsets
from jaxfish.reprojection._lut import ROTATION_TOLERANCE

SRC, DST = jf.Pinhole.from_fov(16, 12, 90.0), jf.Pinhole.from_fov(8, 6, 60.0)


def _yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@pytest.mark.parametrize("matrix,says", [
    (np.diag([-1.0, 1.0, 1.0]), "reflection"),
    (-_yaw(10.0), "reflection"),
    (2.0 * np.eye(3), "not a rotation"),
    (np.full((3, 3), np.nan), "finite"),
    (np.where(np.eye(3) > 0, np.inf, 0.0), "finite"),
])
def test_a_matrix_that_is_not_a_rotation_is_refused(matrix, says):
    with pytest.raises(ValueError, match=f"target_to_source .*{says}"):
        build_lut(SRC, DST, target_to_source=matrix)


def test_rotations_within_the_tolerance_are_accepted_in_every_form():
    r = _yaw(5.0)
    want = build_lut(SRC, DST, target_to_source=r)
    for form in (r.tolist(), r.astype(np.float32), jnp.asarray(r, jnp.float32), r * (1 + ROTATION_TOLERANCE / 4)):
        got = build_lut(SRC, DST, target_to_source=form)
        np.testing.assert_allclose(np.asarray(got.uv), np.asarray(want.uv), atol=1e-3)
    assert bool(build_lut(SRC, DST, target_to_source=np.eye(3, dtype=np.int64)).valid.any())  # the identity as integers
    with pytest.raises(ValueError, match="not a rotation"):
        build_lut(SRC, DST, target_to_source=r * (1 + 4 * ROTATION_TOLERANCE))


def test_a_traced_reflection_raises_at_run_time():
    make = jax.jit(build_lut, static_argnames=("supersample", "dtype"))
    assert bool(make(SRC, DST, target_to_source=jnp.asarray(_yaw(5.0))).valid.any())
    for bad in (np.diag([-1.0, 1.0, 1.0]), np.full((3, 3), np.nan)):
        with pytest.raises((RuntimeError, ValueError), match="target_to_source is not a finite rotation"):  # jax raises either
            jax.block_until_ready(make(SRC, DST, target_to_source=jnp.asarray(bad)))


@pytest.mark.parametrize("dtype", [jnp.int32, jnp.uint8, jnp.bool_, jnp.complex64])
def test_a_non_floating_dtype_is_refused(dtype):
    with pytest.raises(TypeError, match="float32 or float64"):
        build_lut(SRC, DST, dtype=dtype)


@pytest.mark.parametrize("supersample,error", [(2.7, TypeError), (2.0, TypeError), (True, TypeError), ("2", TypeError),
                                               (0, ValueError), (-1, ValueError)])
def test_a_supersample_that_is_not_an_integer_of_at_least_one_is_refused(supersample, error):
    with pytest.raises(error, match="supersample must be"):
        build_lut(SRC, DST, supersample=supersample)
    with pytest.raises(error, match="supersample must be"):
        compiled_build_lut(SRC, DST, supersample=supersample)
    with pytest.raises(error, match="supersample must be"):
        supersample_offsets(supersample)


def test_integer_supersamples_still_work():
    assert build_lut(SRC, DST, supersample=np.int64(2)).uv.shape == (6, 8, 4, 2)
    assert build_lut(SRC, DST, supersample=3).supersample == 3
