"""Grid renders are differentiable in what the splat multiplies: the gradient of a loss on a
grid image with respect to a path's coating tint matches central finite differences (the losses
evaluated in float64 from the float32 images), and it is finite where rays clip or miss."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflare import rendering

from .grid_cases import scene


def image_loss(direction):
    plan = rendering.plan_grid(scene(direction=direction), paths=[(7, 4), (9, 7)], grid_error=1e-9)
    prepared = rendering.prepare_grid(plan)
    weights = jnp.asarray(np.asarray(plan.spectral.luminance_weights), jnp.float32)

    def layers(tint):
        setup = eqx.tree_at(lambda s: s.path_tint, plan.setup, plan.setup.path_tint.at[0].set(tint))
        return rendering.grid_layers(setup, plan, prepared)[0]

    start = jnp.ones(3, jnp.float32)
    target = 0.6 * jax.lax.stop_gradient(layers(start).sum(axis=0) @ weights)

    def loss(tint):
        image = layers(tint).sum(axis=0) @ weights
        return jnp.sum((image - target) ** 2) * 1e3

    return loss


def test_tint_gradient_matches_finite_differences():
    loss = image_loss((0.04, 0.02, -1.0))
    tint = jnp.asarray([0.9, 1.1, 0.8], jnp.float32)
    gradient = np.asarray(jax.grad(loss)(tint), np.float64)
    h = 1e-2
    numeric = []
    for k in range(3):
        step = np.zeros(3, np.float32)
        step[k] = h
        up, down = float(loss(tint + step)), float(loss(tint - step))
        numeric.append((up - down) / (2 * h))
    numeric = np.asarray(numeric)
    assert np.all(np.abs(numeric) > 0)
    np.testing.assert_allclose(gradient, numeric, rtol=2e-3, atol=1e-6 * np.abs(numeric).max())


def test_tint_gradient_is_finite_where_most_rays_miss():
    loss = image_loss((0.62, 0.0, -1.0))
    gradient = np.asarray(jax.grad(loss)(jnp.ones(3, jnp.float32)))
    assert np.all(np.isfinite(gradient))
