"""DDPM training noise and DDIM sampling (diffusers' DDPMScheduler / DDIMScheduler as Diffusion Policy sets them).

Squared-cosine ("squaredcos_cap_v2") betas, epsilon prediction, predicted samples clipped to [-1, 1], DDIM with
eta = 0 and the final step to alpha = 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def squared_cosine_alphas_cumprod(timesteps: int, max_beta: float = 0.999) -> np.ndarray:
    """(timesteps,) cumulative products of alpha of the squared-cosine schedule (Nichol & Dhariwal 2021)."""

    def alpha_bar(t: float) -> float:
        return math.cos((t + 0.008) / 1.008 * math.pi / 2) ** 2

    betas = np.array([min(1 - alpha_bar((i + 1) / timesteps) / alpha_bar(i / timesteps), max_beta)
                      for i in range(timesteps)])
    return np.cumprod(1.0 - betas).astype(np.float32)


def add_noise(alphas_cumprod: jnp.ndarray, clean: jnp.ndarray, noise: jnp.ndarray,
              timesteps: jnp.ndarray) -> jnp.ndarray:
    """q(x_t | x_0): clean (B, ...) noised to the levels `timesteps` (B,)."""
    alpha = alphas_cumprod[timesteps].reshape((-1,) + (1,) * (clean.ndim - 1))
    return jnp.sqrt(alpha) * clean + jnp.sqrt(1 - alpha) * noise


def ddim_timesteps(train_timesteps: int, inference_steps: int) -> np.ndarray:
    """The noise levels visited by DDIM, highest first: [90, 80, ..., 0] for 100 and 10."""
    return (np.arange(inference_steps) * (train_timesteps // inference_steps))[::-1].copy()


def ddim_sample(predict_noise: Callable[[jnp.ndarray, jnp.ndarray], jnp.ndarray], alphas_cumprod: jnp.ndarray,
                shape: tuple[int, ...], key: jax.Array, inference_steps: int) -> jnp.ndarray:
    """Denoise Gaussian noise of `shape` in `inference_steps` deterministic DDIM steps.

    Args:
      predict_noise: (x_t (B, ...), t (B,) int) -> predicted noise, same shape as x_t.
      alphas_cumprod: (T,) of the training schedule.
    Returns:
      The sample (in [-1, 1]: the last step returns the clipped prediction of the clean sample).
    """
    alphas = jnp.asarray(alphas_cumprod)
    timesteps = ddim_timesteps(alphas.shape[0], inference_steps)
    # DDIM steps from level t to t - T / inference_steps; the last one to alpha = 1 (the clean sample)
    previous = jnp.concatenate([alphas[timesteps[1:]], jnp.ones(1)])

    def step(sample, inputs):
        t, alpha_prev = inputs
        alpha = alphas[t]
        noise = predict_noise(sample, jnp.full(shape[:1], t, jnp.int32))
        clean = jnp.clip((sample - jnp.sqrt(1 - alpha) * noise) / jnp.sqrt(alpha), -1.0, 1.0)
        return jnp.sqrt(alpha_prev) * clean + jnp.sqrt(1 - alpha_prev) * noise, None

    sample, _ = jax.lax.scan(step, jax.random.normal(key, shape), (jnp.asarray(timesteps), previous))
    return sample
