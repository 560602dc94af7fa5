"""The DP3-style policy network (flax linen): observation encoder plus a FiLM-conditioned 1-D temporal U-Net.

Follows DP3's `DP3Encoder` (per-point MLP with LayerNorm, max-pool, projection + LayerNorm; an MLP for the
proprioception) and Diffusion Policy's `ConditionalUnet1D` (Conv1d-GroupNorm-Mish blocks, FiLM scale and bias from
the diffusion-step embedding and the global observation condition). Sequences are laid out (B, time, channels).
"""

from __future__ import annotations

import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.train.config import ModelConfig

TRUNCATED_NORMAL_STD = 0.87962566103423978
"""Standard deviation of a unit normal truncated to [-2, 2] (what flax divides by for a truncated LeCun normal)."""


def mish(x: jnp.ndarray) -> jnp.ndarray:
    return x * jnp.tanh(nn.softplus(x))


class PointCloudEncoder(nn.Module):
    """(..., N, C) points -> (..., out_dim): shared per-point MLP, max over points, projection (DP3's PointNet)."""

    dims: tuple[int, ...]
    out_dim: int

    @nn.compact
    def __call__(self, points: jnp.ndarray) -> jnp.ndarray:
        x = points
        for width in self.dims:
            x = nn.relu(nn.LayerNorm()(nn.Dense(width)(x)))
        return nn.LayerNorm()(nn.Dense(self.out_dim)(x.max(axis=-2)))


class MLP(nn.Module):
    """Dense-ReLU-Dense (DP3's state MLP)."""

    width: int

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        return nn.Dense(self.width)(nn.relu(nn.Dense(self.width)(x)))


def sinusoidal_embedding(timesteps: jnp.ndarray, dim: int) -> jnp.ndarray:
    """(B, dim) sin/cos embedding of diffusion steps (B,)."""
    half = dim // 2
    frequencies = jnp.exp(jnp.arange(half) * -(math.log(10000) / (half - 1)))
    angles = timesteps.astype(jnp.float32)[:, None] * frequencies[None]
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], axis=-1)


class TemporalConv(nn.Module):
    """1-D convolution over (B, L, C) with 'same'-style padding (k // 2), written as one matmul over the k shifted
    copies of the sequence: XLA's CPU convolution is 35-60x slower when the kernel is wider than the sequence (the
    U-Net's coarsest level), and the matmul is as fast as a convolution on a GPU."""

    features: int
    kernel_size: int
    stride: int = 1

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        k, pad = self.kernel_size, self.kernel_size // 2
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        length = (x.shape[1] + 2 * pad - k) // self.stride + 1
        padded = jnp.pad(x, ((0, 0), (pad, pad), (0, 0)))
        shifted = jnp.stack([padded[:, i:i + self.stride * (length - 1) + 1:self.stride] for i in range(k)], axis=2)
        return jnp.einsum("blkc,kco->blo", shifted, kernel) + bias


class ConvBlock(nn.Module):
    """Conv1d -> GroupNorm -> Mish."""

    features: int
    kernel_size: int
    groups: int

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        x = TemporalConv(self.features, self.kernel_size)(x)
        return mish(nn.GroupNorm(num_groups=self.groups)(x))


class ConditionalResidualBlock(nn.Module):
    """Two ConvBlocks; the first one's output is scaled and shifted per channel by a FiLM of the condition."""

    features: int
    kernel_size: int
    groups: int

    @nn.compact
    def __call__(self, x: jnp.ndarray, condition: jnp.ndarray) -> jnp.ndarray:
        out = ConvBlock(self.features, self.kernel_size, self.groups)(x)
        scale, bias = jnp.split(nn.Dense(2 * self.features)(mish(condition)), 2, axis=-1)
        out = scale[:, None, :] * out + bias[:, None, :]
        out = ConvBlock(self.features, self.kernel_size, self.groups)(out)
        residual = x if x.shape[-1] == self.features else TemporalConv(self.features, 1)(x)
        return out + residual


class ConditionalUnet1D(nn.Module):
    """Noise prediction for (B, horizon, action_dim) sequences given a global condition (B, D)."""

    action_dim: int
    down_dims: tuple[int, ...]
    step_embed_dim: int
    kernel_size: int
    groups: int

    @nn.compact
    def __call__(self, sample: jnp.ndarray, timesteps: jnp.ndarray, condition: jnp.ndarray) -> jnp.ndarray:
        step = sinusoidal_embedding(timesteps, self.step_embed_dim)
        step = nn.Dense(self.step_embed_dim)(mish(nn.Dense(4 * self.step_embed_dim)(step)))
        condition = jnp.concatenate([step, condition], axis=-1)
        block = dict(kernel_size=self.kernel_size, groups=self.groups)

        x, skips = sample, []
        for level, width in enumerate(self.down_dims):
            x = ConditionalResidualBlock(width, **block)(x, condition)
            x = ConditionalResidualBlock(width, **block)(x, condition)
            if level > 0:  # as in Diffusion Policy, the first level's output is no skip connection
                skips.append(x)
            if level < len(self.down_dims) - 1:
                x = TemporalConv(width, 3, stride=2)(x)
        for _ in range(2):
            x = ConditionalResidualBlock(self.down_dims[-1], **block)(x, condition)
        for level in reversed(range(len(self.down_dims) - 1)):
            width = self.down_dims[level]
            x = jnp.concatenate([x, skips.pop()], axis=-1)
            x = ConditionalResidualBlock(width, **block)(x, condition)
            x = ConditionalResidualBlock(width, **block)(x, condition)
            x = nn.ConvTranspose(width, (4,), strides=(2,), padding="SAME")(x)
        x = ConvBlock(self.down_dims[0], self.kernel_size, self.groups)(x)
        return TemporalConv(self.action_dim, 1)(x)


class DP3Policy(nn.Module):
    """Observation encoder plus denoiser; `encode` once per prediction, `denoise` once per diffusion step.

    Observations: clouds (B, obs_steps, N, C), proprio (B, obs_steps, P) normalised, instruction (B, E).
    """

    config: ModelConfig
    action_dim: int

    def setup(self):
        c = self.config
        self.cloud_encoder = PointCloudEncoder(c.encoder_dims, c.feature_dim)
        self.proprio_encoder = MLP(c.feature_dim)
        self.instruction_encoder = MLP(c.feature_dim)
        self.unet = ConditionalUnet1D(self.action_dim, c.down_dims, c.step_embed_dim, c.kernel_size, c.groups)

    def encode(self, clouds: jnp.ndarray, proprio: jnp.ndarray, instruction: jnp.ndarray) -> jnp.ndarray:
        """(B, obs_steps * 2 * feature_dim + feature_dim) global condition."""
        per_step = jnp.concatenate([self.cloud_encoder(clouds.astype(jnp.float32)), self.proprio_encoder(proprio)],
                                   axis=-1)
        return jnp.concatenate([per_step.reshape(per_step.shape[0], -1), self.instruction_encoder(instruction)],
                               axis=-1)

    def denoise(self, noisy_actions: jnp.ndarray, timesteps: jnp.ndarray, condition: jnp.ndarray) -> jnp.ndarray:
        return self.unet(noisy_actions, timesteps, condition)

    def __call__(self, noisy_actions, timesteps, clouds, proprio, instruction) -> jnp.ndarray:
        return self.denoise(noisy_actions, timesteps, self.encode(clouds, proprio, instruction))


def init_params(model: DP3Policy, inputs: tuple, seed: int) -> dict:
    """flax's default initialisation (LeCun-normal kernels, zero biases, unit norm scales) drawn with NumPy.

    Same values for the same seed, without compiling the random initialisers: `jax.jit(model.init)` takes about
    50 s on a 2-core CPU even for a small network. `inputs` are example arguments of `model.__call__`.
    """
    from scipy.stats import truncnorm

    abstract = jax.eval_shape(model.init, jax.random.key(0), *inputs)
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        name = path[-1].key
        if name == "kernel":
            std = np.sqrt(1.0 / np.prod(leaf.shape[:-1])) / TRUNCATED_NORMAL_STD
            return jnp.asarray(truncnorm.rvs(-2, 2, size=leaf.shape, random_state=rng) * std, leaf.dtype)
        if name in ("bias", "scale"):
            return jnp.full(leaf.shape, 1.0 if name == "scale" else 0.0, leaf.dtype)
        raise ValueError(f"no initialiser for parameter {jax.tree_util.keystr(path)}")

    return jax.tree_util.tree_map_with_path(draw, abstract)
