"""Numerical helpers shared by the core."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxfish._numerics import materialize


def test_materialize_is_an_identity_for_values_gradients_and_vmap():
    x = jnp.linspace(-1.0, 1.0, 7)
    f = lambda v: jnp.sum(materialize((jnp.sin(v), v > 0), v[0])[0] ** 2)  # noqa: E731
    np.testing.assert_array_equal(np.asarray(materialize(x * 3, x[0])), np.asarray(x * 3))
    for grad in (jax.grad(f), jax.jit(jax.grad(f))):
        np.testing.assert_allclose(np.asarray(grad(x)), np.asarray(2 * jnp.sin(x) * jnp.cos(x)), rtol=1e-12)
    batch = jnp.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(np.asarray(jax.vmap(lambda v: materialize(v + 1, v[0]))(batch)), np.asarray(batch + 1))
    # A NaN token runs the loop zero times: still the identity.
    np.testing.assert_array_equal(np.asarray(materialize(x, jnp.nan)), np.asarray(x))


def test_incidence_angle_equals_atan2_with_exact_gradients():
    from jaxfish._numerics import incidence_angle

    rng = np.random.default_rng(0)
    chi = np.abs(rng.normal(size=20000))
    z = rng.normal(size=20000)
    chi[:6], z[:6] = [0.0, 1.0, 2.0, 0.0, 1e-300, 3.0], [0.0, 1.0, -2.0, -1.0, 1.0, 0.0]  # origin, both 45° ties, axis
    got = np.asarray(jax.jit(incidence_angle)(jnp.asarray(chi), jnp.asarray(z)))
    want = np.arctan2(chi, z)
    np.testing.assert_array_less(np.abs(got - want), 2 * np.spacing(np.maximum(want, 1e-300)) + 1e-300)
    grad = jax.vmap(jax.grad(incidence_angle, argnums=(0, 1)))(jnp.asarray(chi[1:]), jnp.asarray(z[1:]))
    r2 = chi[1:] ** 2 + z[1:] ** 2
    np.testing.assert_allclose(np.asarray(grad[0]), z[1:] / r2, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(grad[1]), -chi[1:] / r2, rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(np.asarray(jax.grad(incidence_angle, argnums=(0, 1))(0.0, 0.0))))


def test_float32_arctan_polynomial_within_a_few_ulp_with_quadrants_and_gradients():
    from jaxfish._numerics import arctan2, arctan_unit, incidence_angle
    from tests import tolerances as tol
    from tests.helpers import three_ways

    a = np.concatenate([np.linspace(0.0, 1.0, 200_001), np.geomspace(1e-30, 1.0, 2000)]).astype(np.float32)
    want = np.arctan(a.astype(np.float64))
    for got in three_ways(arctan_unit, jnp.asarray(a)):
        ulp = np.spacing(np.abs(want).astype(np.float32)).astype(np.float64)
        assert got.dtype == np.float32 and np.max(np.abs(got - want) / ulp) <= tol.ATAN_F32_ULP
    # Every quadrant, the axes and signed zeros, as IEEE atan2; float64 is jnp.arctan2 itself.
    rng = np.random.default_rng(1)
    y = np.concatenate([rng.normal(size=5000), [0.0, -0.0, 0.0, -0.0, 1.0, -1.0, 2.0, -2.0]]).astype(np.float32)
    x = np.concatenate([rng.normal(size=5000), [0.0, 0.0, -0.0, -0.0, 0.0, -0.0, -2.0, 2.0]]).astype(np.float32)
    want = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    got = np.asarray(jax.jit(arctan2)(jnp.asarray(y), jnp.asarray(x))).astype(np.float64)
    assert np.max(np.abs(got - want)) <= tol.ATAN_F32_ULP * np.spacing(np.float32(np.pi))
    np.testing.assert_array_equal(np.signbit(got[-8:]), np.signbit(want[-8:]))
    y64, x64 = y.astype(np.float64), x.astype(np.float64)
    np.testing.assert_array_equal(np.asarray(arctan2(jnp.asarray(y64), jnp.asarray(x64))), np.asarray(jnp.arctan2(y64, x64)))
    # Gradients in float32: finite everywhere (the origin included), close to the analytic ones.
    chi, z = np.abs(y[:5000]), x[:5000]
    g = jax.vmap(jax.grad(incidence_angle, argnums=(0, 1)))(jnp.asarray(chi), jnp.asarray(z))
    r2 = chi.astype(np.float64) ** 2 + z.astype(np.float64) ** 2
    np.testing.assert_allclose(np.asarray(g[0]), z / r2, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(g[1]), -chi / r2, rtol=1e-4, atol=1e-6)
    assert np.all(np.isfinite(np.asarray(jax.grad(incidence_angle, argnums=(0, 1))(jnp.float32(0), jnp.float32(0)))))


def test_safe_sqrt_is_zero_with_finite_gradients_at_and_below_zero():
    from jaxfish._numerics import safe_sqrt

    x = jnp.asarray([-4.0, -1e-300, 0.0, 1e-300, 0.25, 9.0])
    np.testing.assert_array_equal(np.asarray(safe_sqrt(x)), np.sqrt(np.maximum(np.asarray(x), 0.0)))
    g = np.asarray(jax.vmap(jax.grad(safe_sqrt))(x))
    assert np.all(np.isfinite(g)) and np.all(g[:3] == 0.0)
    np.testing.assert_allclose(g[4:], 0.5 / np.sqrt(np.asarray(x[4:])), rtol=1e-15)
