"""A `gymnasium.Env` serving one PartInstruct environment on the CPU (`mujoco`) backend."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import jax
import numpy as np

from partinstruct_mjx.env import EnvConfig, PartInstructEnv
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.tasks.progress import MAX_SKILLS


class PartInstructGymEnv(gym.Env):
    """One scene of `object_xml`; each reset draws one of `episodes` (or `options={"episode": i}`).

    Observations: tcp_pose [qx, qy, qz, qw, x, y, z], joint_states (7), gripper_state (1), instruction_index.
    Actions: x, y, z, roll, pitch, yaw (extrinsic 'xyz'), finger opening in metres (0 ... 0.04).
    `terminated` is success; `truncated` is the step limit (250, 400 for test4) or a diverged simulation
    (`PartInstructEnv`'s `info["unstable"]`). `info["instruction"]` is the
    instruction the policy should follow now.
    """

    metadata = {"render_modes": []}

    def __init__(self, object_xml: str | Path, episodes: list, config: EnvConfig = EnvConfig()):
        if config.backend != "mujoco" or config.rotation != "euler":
            raise TaskError("the gymnasium wrapper serves the 'mujoco' backend with Euler actions")
        if not episodes:
            raise TaskError("the gymnasium wrapper needs at least one episode")
        self.episodes = list(episodes)
        self.env = PartInstructEnv(object_xml, 1, config)
        self.state = None
        self.action_space = gym.spaces.Box(
            low=np.array([-1.0, -1.0, 0.0, -np.pi, -np.pi, -np.pi, panda.FINGER_CLOSED], np.float32),
            high=np.array([1.5, 1.0, 1.2, np.pi, np.pi, np.pi, panda.FINGER_OPEN], np.float32))
        self.observation_space = gym.spaces.Dict({
            "tcp_pose": gym.spaces.Box(-np.inf, np.inf, (7,), np.float32),
            "joint_states": gym.spaces.Box(-np.inf, np.inf, (7,), np.float32),
            "gripper_state": gym.spaces.Box(0.0, panda.FINGER_OPEN, (1,), np.float32),
            "instruction_index": gym.spaces.Discrete(MAX_SKILLS + 1),
        })

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        index = (options or {}).get("episode", int(self.np_random.integers(len(self.episodes))))
        if not 0 <= index < len(self.episodes):
            raise TaskError(f"episode index {index} is out of range (0..{len(self.episodes) - 1})")
        key = jax.random.PRNGKey(int(self.np_random.integers(2**31)))
        self.state = self.env.reset(key, [self.episodes[index]])
        return self._observation(), self._info()

    def step(self, action):
        if self.state is None:
            raise TaskError("call reset() before step()")
        self.state = self.env.step(self.state, np.asarray(action, np.float32)[None])
        terminated = bool(self.state.task.success[0])
        truncated = bool(self.state.info["truncated"][0])
        return self._observation(), float(self.state.reward[0]), terminated, truncated, self._info()

    def close(self):
        self.env.close()

    def _observation(self) -> dict:
        obs = self.state.obs
        return {"tcp_pose": np.asarray(obs["tcp_pose"][0], np.float32),
                "joint_states": np.asarray(obs["joint_states"][0], np.float32),
                "gripper_state": np.clip(np.asarray(obs["gripper_state"][0], np.float32), 0.0, panda.FINGER_OPEN),
                "instruction_index": int(obs["instruction_index"][0])}

    def _info(self) -> dict:
        metrics = {k: np.asarray(v[0]).item() for k, v in self.state.metrics.items()}
        return {**metrics, "instruction": self.env.instructions(self.state)[0],
                "steps": int(self.state.info["steps"][0])}
