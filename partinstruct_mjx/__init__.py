"""partinstruct-mjx: the PartInstruct part-level manipulation benchmark on MuJoCo with batched JAX rollouts."""

from partinstruct_mjx.jax_setup import set_xla_flags

set_xla_flags()

from partinstruct_mjx.errors import AssetError, PartInstructError, SceneError  # noqa: E402
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend  # noqa: E402
from partinstruct_mjx.sim.scene import Scene, SceneConfig, build_scene  # noqa: E402
from partinstruct_mjx.sim.state import SceneState  # noqa: E402

__version__ = "0.1.0"
__all__ = [
    "AssetError",
    "MujocoBackend",
    "PartInstructError",
    "Scene",
    "SceneConfig",
    "SceneError",
    "SceneState",
    "build_scene",
]
