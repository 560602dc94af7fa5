"""The Brax environment on MJX: the Env interface, input checks, and (slow) wrapped rollouts against the C backend."""

import time
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

brax_base = pytest.importorskip("brax.envs.base")

from partinstruct_mjx import paths  # noqa: E402
from partinstruct_mjx.brax_env import OBSERVATION_SIZE, BraxPartInstructEnv  # noqa: E402
from partinstruct_mjx.env import EnvConfig, PartInstructEnv, hold_action  # noqa: E402
from partinstruct_mjx.errors import SceneError, TaskError  # noqa: E402
from partinstruct_mjx.tasks import progress  # noqa: E402
from partinstruct_mjx.tasks.episodes import Episode  # noqa: E402
from partinstruct_mjx.tasks.task_types import task_type  # noqa: E402

BOTTLE = paths.assets_root() / "objects" / "bottle" / "bottle_000" / "object.xml"


def _episode(type_id=1, parts=None, directions=None, xy=(0.0, -0.03), split="train", obj=("bottle", "bottle_000")):
    chain = task_type(type_id).build_chain(parts or {"P1": "body"}, directions or {"D1": "left"})
    return Episode(obj_class=obj[0], obj_id=obj[1], ep_id=type_id, task_type=type_id, split=split,
                   chain=tuple(chain), task_instruction=f"task {type_id}",
                   skill_instructions=tuple(f"skill {i} of {type_id}" for i in range(len(chain))),
                   obj_pose=(0.0, 0.0, 0.0, 1.0, xy[0], xy[1], 0.0), obj_scale=1.0)


EPISODES = [_episode(1), _episode(3, {"P1": "lid"}, xy=(0.05, 0.1))]


@pytest.fixture(scope="module")
def env():
    return BraxPartInstructEnv(BOTTLE, EPISODES)


def test_is_a_brax_env_with_the_right_sizes(env):
    assert isinstance(env, brax_base.Env)
    assert env.observation_size == OBSERVATION_SIZE == 7 + 7 + 1 + progress.MAX_SKILLS
    assert env.action_size == 7 and env.backend == "mjx" and env.dt == pytest.approx(0.05)
    assert env.episode_length == 250
    reset = jax.eval_shape(env.reset, jax.random.PRNGKey(0))  # traces, does not compile
    assert reset.obs.shape == (env.observation_size,) and reset.obs.dtype == jnp.float32
    assert reset.reward.shape == reset.done.shape == () and reset.done.dtype == jnp.float32
    assert set(reset.metrics) == {"success", "completion", "skill_index", "phase", "goal_0", "goal_1", "goal_2",
                                  "goal_3"}
    assert set(reset.info) == {"episode", "joint_targets", "env_steps"}
    stepped = jax.eval_shape(env.step, reset, jax.ShapeDtypeStruct((7,), jnp.float32))
    # Brax's wrappers scan and select between reset and stepped states: same tree, shapes and dtypes.
    assert jax.tree.structure(stepped) == jax.tree.structure(reset)
    assert all(jax.tree.leaves(jax.tree.map(lambda a, b: (a.shape, a.dtype) == (b.shape, b.dtype), reset, stepped)))


def test_brax_training_wrappers_trace(env):
    """wrap() plus EvalWrapper (what brax.training's PPO uses) trace: metrics and info that wrappers add survive."""
    from brax.envs.wrappers import training

    wrapped = training.EvalWrapper(training.wrap(env, episode_length=4))
    reset = jax.eval_shape(wrapped.reset, jax.random.split(jax.random.PRNGKey(0), 2))
    stepped = jax.eval_shape(wrapped.step, reset, jax.ShapeDtypeStruct((2, 7), jnp.float32))
    assert stepped.obs.shape == (2, OBSERVATION_SIZE) and "reward" in stepped.metrics
    assert jax.tree.structure(stepped) == jax.tree.structure(reset)


def test_quaternion_actions_and_long_test4_episodes():
    long = _episode(12, {"P1": "body", "P2": "lid"}, {"D1": "left", "D2": "front"}, split="test4")
    env = BraxPartInstructEnv(BOTTLE, [long, _episode(1)], EnvConfig(backend="mjx", rotation="quat"))
    assert env.action_size == 8 and env.episode_length == 400
    reset = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    assert jax.eval_shape(env.step, reset, jax.ShapeDtypeStruct((8,), jnp.float32)).obs.shape == (OBSERVATION_SIZE,)


def test_instructions_follow_episode_and_skill(env):
    def state(episode, skill):
        return SimpleNamespace(pipeline_state=SimpleNamespace(episode=np.asarray(episode),
                                                              task=SimpleNamespace(skill_index=np.asarray(skill))))

    assert env.instructions(state([1, 0], [1, 5])) == ["skill 1 of 3", "skill 0 of 1"]  # past the end: last skill
    assert env.instructions(state(1, 1)) == "skill 1 of 3"


def test_bad_input_raises_clear_errors(env):
    with pytest.raises(TaskError, match="at least one episode, got an empty list"):
        BraxPartInstructEnv(BOTTLE, [])
    with pytest.raises(TaskError, match="episode 1 is for object 'mug_000'.*'bottle_000'"):
        BraxPartInstructEnv(BOTTLE, [_episode(1), _episode(1, {"P1": "handle"}, obj=("mug", "mug_000"))])
    with pytest.raises(TaskError, match="unknown part 'handle'"):
        BraxPartInstructEnv(BOTTLE, [_episode(1, {"P1": "handle"})])
    with pytest.raises(SceneError, match="backend must be 'mjx', got 'mujoco'"):
        BraxPartInstructEnv(BOTTLE, EPISODES, EnvConfig(backend="mujoco"))
    with pytest.raises(SceneError, match="object_noise must be 0, got 0.01"):
        BraxPartInstructEnv(BOTTLE, EPISODES, EnvConfig(backend="mjx", object_noise=0.01))
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    with pytest.raises(TaskError, match=r"action must have shape \(7,\) for rotation='euler', got \(6,\)"):
        env.step(state, np.zeros(6))
    with pytest.raises(TaskError, match=r"got \(2, 7\).*VmapWrapper"):
        env.step(state, np.zeros((2, 7)))


def _hold(tcp_pose: np.ndarray) -> np.ndarray:
    """The Euler actions that keep the TCP where it is, fingers open."""
    return hold_action(tcp_pose)


def _rows(tree, row):
    return jax.tree.map(lambda x: np.asarray(x)[row], tree)


@pytest.mark.slow
def test_wrapped_rollout_matches_the_c_backend_and_auto_resets(env):
    """wrap() (vmap + episode limit + auto-reset) around the env, batch 2: jitted reset and steps agree with
    PartInstructEnv(backend='mujoco') within 1 mm (docs/differences.md #24), and finished episodes start over.
    Compiles reset (~15 s) and step (~20 s) on a CPU."""
    from brax.envs.wrappers import training

    from partinstruct_mjx.jax_setup import enable_compilation_cache

    enable_compilation_cache()
    wrapped = training.wrap(env, episode_length=4)
    reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
    start = time.perf_counter()
    state = jax.block_until_ready(reset(jax.random.split(jax.random.PRNGKey(3), 2)))
    print(f"reset compile + run {time.perf_counter() - start:.1f} s")
    first = state
    drawn = [int(i) for i in state.pipeline_state.episode]
    assert np.array_equal(np.asarray(state.info["episode"]), drawn)

    with PartInstructEnv(BOTTLE, 2, EnvConfig(backend="mujoco")) as reference:
        ref = reference.reset(jax.random.PRNGKey(0), [EPISODES[i] for i in drawn])
        np.testing.assert_allclose(state.obs[:, :7], ref.obs["tcp_pose"], atol=1e-4)
        np.testing.assert_allclose(state.obs[:, 7:14], ref.obs["joint_states"], atol=1e-4)
        np.testing.assert_allclose(state.pipeline_state.scene.object_pos, ref.data.object_pos, atol=1e-4)
        action = _hold(np.asarray(ref.obs["tcp_pose"]))
        for i in range(3):
            action[:, 2] -= 0.004
            start = time.perf_counter()
            state = jax.block_until_ready(step(state, jnp.asarray(action)))
            print(f"step {i}: {time.perf_counter() - start:.2f} s")
            ref = reference.step(ref, action)
        ours = state.pipeline_state.scene
        np.testing.assert_allclose(ours.tcp_pos, ref.data.tcp_pos, atol=1e-3)
        np.testing.assert_allclose(ours.object_pos, ref.data.object_pos, atol=1e-4)
        np.testing.assert_allclose(state.obs[:, 14], np.asarray(ref.obs["gripper_state"])[:, 0], atol=1e-4)
        np.testing.assert_array_equal(state.metrics["completion"], ref.metrics["completion"])
        np.testing.assert_array_equal(state.metrics["success"], ref.metrics["success"])
        np.testing.assert_allclose(state.info["joint_targets"], ref.info["joint_targets"], atol=1e-4)
    assert not state.done.any() and list(np.asarray(state.info["env_steps"])) == [3, 3]
    moved = np.asarray(ours.qpos)

    # Step 4 reaches the episode limit: done (truncated), and both environments are back at their first state.
    state = step(state, jnp.asarray(action))
    assert np.asarray(state.done).all() and np.asarray(state.info["truncation"]).all()
    np.testing.assert_array_equal(state.pipeline_state.scene.qpos, first.pipeline_state.scene.qpos)
    np.testing.assert_array_equal(state.obs, first.obs)
    assert not np.allclose(moved, np.asarray(first.pipeline_state.scene.qpos))

    # Success ends an episode too: make environment 0's chain one skill of padding goals (always met).
    task = state.pipeline_state.task
    hacked = task.replace(skills=task.skills.replace(kind=task.skills.kind.at[0].set(0)),
                          num_skills=task.num_skills.at[0].set(1))
    state = step(state.replace(pipeline_state=state.pipeline_state.replace(task=hacked)), jnp.asarray(action))
    assert list(np.asarray(state.done)) == [1.0, 0.0] and list(np.asarray(state.reward)) == [1.0, 0.0]
    assert list(np.asarray(state.metrics["success"])) == [1.0, 0.0]
    assert list(np.asarray(state.info["truncation"])) == [0.0, 0.0]
    restored = _rows(state.pipeline_state, 0)  # auto-reset put back the physics and the task progress
    for got, want in zip(jax.tree.leaves(restored), jax.tree.leaves(_rows(first.pipeline_state, 0))):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(state.obs[0], first.obs[0])

    state = step(state, jnp.asarray(action))
    assert not np.asarray(state.done).any() and not np.asarray(state.metrics["success"]).any()
    assert list(np.asarray(state.pipeline_state.steps)) == [1, 2]
