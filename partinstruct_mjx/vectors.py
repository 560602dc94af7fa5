"""3-vector arithmetic over point clouds, written out per coordinate.

XLA on a CPU runs a dot product with the 3-axis as its contraction (`points @ direction`) as a batched matrix product
and a norm over the 3-axis as a reduction, both slow for thousands of points; written out per coordinate they fuse
with what surrounds them into one elementwise loop (the oracle's step ran 4x faster this way).
"""

from __future__ import annotations

import jax.numpy as jnp


def dot3(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """a . b over the last axis (size 3) of broadcast arrays."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def squared_norm(v: jnp.ndarray) -> jnp.ndarray:
    """|v|^2 over the last axis (size 3)."""
    return dot3(v, v)


def norm3(v: jnp.ndarray) -> jnp.ndarray:
    """|v| over the last axis (size 3)."""
    return jnp.sqrt(squared_norm(v))
