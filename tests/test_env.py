"""The batched environment on the C backend (and against MJX in the slow suite)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from partinstruct_mjx import paths
from partinstruct_mjx.env import EnvConfig, PartInstructEnv, hold_action
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.sim.scene import SceneConfig
from partinstruct_mjx.tasks.episodes import Episode
from partinstruct_mjx.tasks.task_types import task_type

MUG = paths.assets_root() / "objects" / "mug" / "mug_000" / "object.xml"


def _episode(type_id=3, split="train", parts=None, directions=None, xy=(0.0, -0.03)):
    chain = task_type(type_id).build_chain(parts or {"P1": "handle", "P2": "handle", "P3": "body"},
                                           directions or {"D1": "left", "D2": "front"})
    return Episode(obj_class="mug", obj_id="mug_000", ep_id=0, task_type=type_id, split=split, chain=tuple(chain),
                   task_instruction="Hold the mug by its handle and move it to the left",
                   skill_instructions=tuple(f"skill {i}" for i in range(len(chain))),
                   obj_pose=(0.0, 0.0, 0.0, 1.0, xy[0], xy[1], 0.0), obj_scale=1.0)


@pytest.fixture(scope="module")
def env():
    with PartInstructEnv(MUG, 2) as env:
        yield env


def _hold(state, finger=0.04):
    """The action that keeps the TCP where it is."""
    return hold_action(state.obs["tcp_pose"], finger)


def test_reset_observations_in_the_original_layout(env):
    state = env.reset(jax.random.PRNGKey(0), [_episode(), _episode(1, xy=(0.05, 0.1))])
    pose = np.asarray(state.obs["tcp_pose"])
    np.testing.assert_allclose(pose[:, 4:], [[0.5748, 0.5751, 0.3478]] * 2, atol=5e-4)  # spec 1.3 home TCP
    np.testing.assert_allclose(np.abs(pose[0, :4]), np.abs([0.2656, 0.9591, -0.0876, -0.0446]), atol=5e-4)
    assert state.obs["joint_states"].shape == (2, 7) and state.obs["gripper_state"].shape == (2, 1)
    np.testing.assert_allclose(np.asarray(state.data.object_pos)[:, :2], [[0.0, -0.03], [0.05, 0.1]], atol=2e-3)
    assert not state.done.any() and set(state.metrics) >= {"success", "completion", "goal_0"}
    assert env.instructions(state) == ["skill 0", "skill 0"]


def test_pose_actions_move_the_tcp_through_ik(env):
    state = env.reset(jax.random.PRNGKey(0), [_episode(), _episode()])
    action = _hold(state)
    action[:, 2] -= 0.05  # 5 cm down
    action[1, 1] -= 0.03  # and 3 cm right for the second scene
    start = np.asarray(state.obs["tcp_pose"])[:, 4:]
    for _ in range(20):  # 1 s
        state = env.step(state, action)
    moved = np.asarray(state.obs["tcp_pose"])[:, 4:] - start
    np.testing.assert_allclose(moved, [[0, 0, -0.05], [0, -0.03, -0.05]], atol=1e-3)
    assert (np.asarray(state.info["steps"]) == 20).all()


def test_inactive_scenes_are_not_simulated(env):
    """`step(state, action, active)`: on the mujoco backend a scene outside `active` keeps its physics as it was."""
    state = env.reset(jax.random.PRNGKey(0), [_episode(), _episode()])
    action = _hold(state)
    action[:, 2] -= 0.05
    start = np.asarray(state.obs["tcp_pose"])[:, 4:]
    for _ in range(5):
        state = env.step(state, action, np.array([True, False]))
    moved = np.asarray(state.obs["tcp_pose"])[:, 4:] - start
    assert moved[0, 2] < -0.005
    np.testing.assert_array_equal(moved[1], 0.0)


def test_quaternion_actions_match_euler_actions():
    episodes = [_episode(), _episode()]
    results = []
    for rotation in ("euler", "quat"):
        with PartInstructEnv(MUG, 2, EnvConfig(rotation=rotation, scene=SceneConfig(settle_steps=5))) as env:
            state = env.reset(jax.random.PRNGKey(0), episodes)
            pose = np.asarray(state.obs["tcp_pose"])
            if rotation == "euler":
                action = _hold(state)
            else:
                action = np.concatenate([pose[:, 4:], np.roll(pose[:, :4], 1, axis=1), np.full((2, 1), 0.04)], 1)
            action[:, 0] += 0.02
            for _ in range(5):
                state = env.step(state, action)
            results.append(np.asarray(state.data.qpos))
    np.testing.assert_allclose(results[0], results[1], atol=1e-5)


def test_step_limits_and_truncation():
    with PartInstructEnv(MUG, 2, EnvConfig(scene=SceneConfig(settle_steps=1))) as env:
        state = env.reset(jax.random.PRNGKey(0), [_episode(split="test1"), _episode(12, split="test4")])
        assert list(np.asarray(state.info["step_limit"])) == [250, 400]
        action = _hold(state)
        state = state.replace(info={**state.info, "steps": jnp.asarray([249, 399])})
        state = env.step(state, action)
        assert list(np.asarray(state.done)) == [True, True] and np.asarray(state.info["truncated"]).all()


def test_a_diverged_simulation_ends_its_episode_without_success(env):
    """MuJoCo resets a scene whose simulation diverges; the env ends that episode, failed, until the scene is reset,
    and a restored snapshot (the oracle's backtracking) is stable again."""
    state = env.reset(jax.random.PRNGKey(0), [_episode(), _episode()])
    physics = env.backend.get_physics_state()
    broken = physics.copy()
    broken[1, 1 + env.backend.model.nq] = np.nan  # scene 1's first joint velocity (the state starts with time, qpos)
    env.backend.set_physics_state(broken, np.array([False, True]))
    state = env.step(state, _hold(state))
    assert list(np.asarray(state.info["unstable"])) == [False, True]
    assert list(np.asarray(state.done)) == [False, True] and np.asarray(state.info["truncated"])[1]
    assert not np.asarray(state.task.success)[1] and np.isfinite(np.asarray(state.data.qpos)).all()
    env.backend.restore(physics, np.array([False, True]))
    assert not env.backend.unstable().any()
    state = env.reset_rows(state, jax.random.PRNGKey(0), np.array([False, True]), [_episode()])
    assert not np.asarray(env.step(state, _hold(state)).info["unstable"]).any()


def test_bad_input_raises_clear_errors(env):
    with pytest.raises(TaskError, match="reset needs 2 episodes, got 1"):
        env.reset(jax.random.PRNGKey(0), [_episode()])
    with pytest.raises(TaskError, match="unknown part 'spout'"):
        env.reset(jax.random.PRNGKey(0), [_episode(), _episode(parts={"P1": "spout"})])
    state = env.reset(jax.random.PRNGKey(0), [_episode(), _episode()])
    with pytest.raises(TaskError, match=r"action must have shape \(2, 7\)"):
        env.step(state, np.zeros((2, 6)))


@pytest.mark.slow
def test_mujoco_and_mjx_backends_agree_on_a_short_episode():
    """Same episode, same actions: the C and MJX backends end within 1 mm (MJX compiles ~40 s on CPU).

    With unsaturated servos they agree to 1e-7; while a joint servo saturates at its torque limit MJX's
    implicit integrator keeps the servo's velocity gain and C MuJoCo drops it, which leaves ~0.5 mm here. The mug
    rests 0.3 mm deeper in C MuJoCo: since converter version 4 its base hull is flat, and the two collision
    pipelines (C's with its no-slip pass, MJX's without) settle a face on the table to different depths (they agreed
    to 1e-4 while the base touched the table at one vertex).
    """
    episodes = [_episode(), _episode(1)]
    finals = []
    for backend in ("mujoco", "mjx"):
        config = EnvConfig(backend=backend, scene=SceneConfig(settle_steps=3))
        with PartInstructEnv(MUG, 2, config) as env:
            state = env.reset(jax.random.PRNGKey(0), episodes)
            action = _hold(state)
            for step in range(6):
                action[:, 2] -= 0.004
                state = env.step(state, action)
            finals.append((np.asarray(state.data.tcp_pos), np.asarray(state.data.object_pos),
                           np.asarray(state.metrics["completion"])))
    np.testing.assert_allclose(finals[0][0], finals[1][0], atol=1e-3)
    np.testing.assert_allclose(finals[0][1], finals[1][1], atol=5e-4)
    np.testing.assert_array_equal(finals[0][2], finals[1][2])


def test_camera_and_point_cloud_observations_mark_the_target_part(env):
    """Skill 0 grasps the handle: both paths mark handle points and pixels, with spec 2.1's keys and shapes; a move
    skill has no target part."""
    state = env.reset(jax.random.PRNGKey(0), [_episode(3), _episode(5)])
    assert list(env.target_parts(state)) == [env.part_names.index("handle")] * 2
    clouds = env.point_clouds(state, jax.random.PRNGKey(1))
    assert clouds["agentview_pcd"].shape == (2, 1024, 3) and clouds["agentview_part_pcd"].shape == (2, 1024, 4)
    assert np.asarray(clouds["agentview_part_pcd"][..., 3]).sum() > 0
    observations = env.camera_observations(state, wrist=True)
    first = observations[0]
    assert first["agentview_rgb"].shape == (300, 300, 3) and first["agentview_rgb"].dtype == np.uint8
    assert first["agentview_part_mask"].shape == (300, 300) and first["agentview_part_mask"].sum() > 0
    assert first["agentview_part_pcd"].shape == (1024, 4) and first["wrist_rgb"].shape == (300, 300, 3)
    moved = state.replace(task=state.task.replace(skill_index=jnp.asarray([1, 1])))  # move: no target part
    assert list(env.target_parts(moved)) == [-1, -1]
    assert env.camera_observations(moved)[0]["agentview_part_mask"].sum() == 0
