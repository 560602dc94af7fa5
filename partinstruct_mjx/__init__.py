"""partinstruct-mjx: the PartInstruct part-level manipulation benchmark on MuJoCo with batched JAX rollouts.

The public names below are imported on first use, so `import partinstruct_mjx` stays cheap (no JAX, no MuJoCo)
for tools and worker processes that need only a part of the package.
"""

from partinstruct_mjx.jax_setup import set_xla_flags
from partinstruct_mjx.lazy import lazy_getattr

set_xla_flags()

__version__ = "0.1.0"

_PUBLIC = {
    "AssetError": "partinstruct_mjx.errors",
    "PartInstructError": "partinstruct_mjx.errors",
    "SceneError": "partinstruct_mjx.errors",
    "TaskError": "partinstruct_mjx.errors",
    "EnvConfig": "partinstruct_mjx.env",
    "PartInstructEnv": "partinstruct_mjx.env",
    "BraxPartInstructEnv": "partinstruct_mjx.brax_env",
    "PartInstructGymEnv": "partinstruct_mjx.gym_env",
    "load_catalog": "partinstruct_mjx.assets.catalog",
    "read_metadata": "partinstruct_mjx.tasks.episodes",
    "MujocoBackend": "partinstruct_mjx.sim.mujoco_backend",
    "Scene": "partinstruct_mjx.sim.scene",
    "SceneConfig": "partinstruct_mjx.sim.scene",
    "build_scene": "partinstruct_mjx.sim.scene",
    "SceneState": "partinstruct_mjx.sim.state",
}
__all__ = sorted(_PUBLIC)

__getattr__ = lazy_getattr(__name__, _PUBLIC)
