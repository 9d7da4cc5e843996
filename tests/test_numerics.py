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
