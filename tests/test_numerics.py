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
