"""Policy training: demos -> windows -> a DP3-style diffusion policy (flax + optax + orbax) -> an evaluator policy.

Public names are imported on first use, so the CLI can read the configuration without loading JAX.
"""

from partinstruct_mjx.lazy import lazy_getattr

_PUBLIC = {
    "ModelConfig": "partinstruct_mjx.train.config",
    "TrainConfig": "partinstruct_mjx.train.config",
    "POLICIES": "partinstruct_mjx.train.config",
    "load_demos": "partinstruct_mjx.train.dataset",
    "WindowSampler": "partinstruct_mjx.train.dataset",
    "InstructionEmbeddings": "partinstruct_mjx.train.language",
    "train": "partinstruct_mjx.train.trainer",
    "DiffusionPolicy": "partinstruct_mjx.train.policy",
    "load_policy": "partinstruct_mjx.train.policy",
}
__all__ = sorted(_PUBLIC)

__getattr__ = lazy_getattr(__name__, _PUBLIC)
