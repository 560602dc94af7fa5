"""The gymnasium wrapper: passes gymnasium's checker, steps, terminates and truncates."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from partinstruct_mjx.env import EnvConfig
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.gym_env import PartInstructGymEnv
from partinstruct_mjx.sim.scene import SceneConfig
from tests.test_env import MUG, _episode


@pytest.fixture(scope="module")
def gym_env():
    env = PartInstructGymEnv(MUG, [_episode(), _episode(1, xy=(0.05, 0.1))],
                             EnvConfig(scene=SceneConfig(settle_steps=5)))
    yield env
    env.close()


def test_passes_the_gymnasium_checker(gym_env):
    check_env(gym_env, skip_render_check=True)


def test_episode_choice_steps_and_truncation(gym_env):
    obs, info = gym_env.reset(seed=3, options={"episode": 1})
    assert gym_env.observation_space.contains(obs)
    assert info["instruction"] == "skill 0" and info["steps"] == 0
    action = np.concatenate([obs["tcp_pose"][4:], [np.pi, 0.0, 0.0], [0.04]]).astype(np.float32)
    obs, reward, terminated, truncated, info = gym_env.step(action)
    assert info["steps"] == 1 and reward == 0.0 and not terminated and not truncated
    gym_env.state = gym_env.state.replace(info={**gym_env.state.info,
                                                "steps": gym_env.state.info["steps"] + 248})
    *_, truncated, info = gym_env.step(action)
    assert truncated and info["steps"] == 250


def test_bad_use_raises_clear_errors(gym_env):
    with pytest.raises(TaskError, match="episode index 5 is out of range"):
        gym_env.reset(options={"episode": 5})
    with pytest.raises(TaskError, match="at least one episode"):
        PartInstructGymEnv(MUG, [])
    assert isinstance(gym_env, gym.Env)
