"""The C-MuJoCo batched backend: home pose, settling, batch determinism, state contents, errors."""

import numpy as np
import pytest

from partinstruct_mjx.bench.cpu_backend import moving_controls
from partinstruct_mjx.control.scripted_pick import PickConfig, run_pick
from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import TABLE_HEIGHT, random_placements
from partinstruct_mjx.sim.state import body_rows


def _placements(batch, seed=0):
    return random_placements(batch, seed)


def test_robot_holds_its_home_pose(scene):
    with MujocoBackend(scene, 2) as backend:
        state = backend.reset()
        for _ in range(100):  # 5 s
            state = backend.step(np.tile(panda.HOME_CTRL, (2, 1)))
    np.testing.assert_allclose(state.arm_qpos, np.tile(panda.HOME_ARM_QPOS, (2, 1)), atol=1e-4)
    np.testing.assert_allclose(state.finger_qpos, panda.FINGER_OPEN, atol=1e-4)
    np.testing.assert_allclose(state.tcp_pos[0], [0.5748, 0.5751, 0.3478], atol=5e-4)
    assert np.abs(state.qvel[:, scene.arm_dof_adr]).max() < 1e-3


def test_object_settles_without_jitter_or_penetration(scene):
    xy, quat = _placements(4)
    with MujocoBackend(scene, 4) as backend:
        settled = backend.reset(xy, quat)
        trajectory = []
        for _ in range(40):  # 2 more seconds at rest
            state = backend.step(np.tile(panda.HOME_CTRL, (4, 1)))
            trajectory.append(state.object_pos.copy())
        depths = [min(0.0, d.contact.dist[: d.ncon].min(initial=0.0)) for d in backend.datas]
    trajectory = np.array(trajectory)
    np.testing.assert_allclose(settled.object_pos[:, :2], xy, atol=2e-3)     # dropped where asked, no sliding
    np.testing.assert_allclose(settled.object_pos[:, 2], TABLE_HEIGHT, atol=1e-3)  # origin at the block's bottom
    assert np.abs(trajectory - settled.object_pos).max() < 1e-4              # no jitter while resting
    assert np.abs(state.qvel[:, scene.object_dof_adr:]).max() < 1e-3
    assert min(depths) > -1e-3                                                # < 1 mm penetration


def test_batch_equals_one_by_one(scene):
    """Stepping 8 environments together gives exactly the states of stepping each alone."""
    batch, steps = 8, 30
    xy, quat = _placements(batch, seed=1)
    controls = moving_controls(batch, steps, seed=2)
    with MujocoBackend(scene, batch, num_threads=2) as backend:
        backend.reset(xy, quat)
        for ctrl in controls:
            together = backend.step(ctrl)
    for i in range(batch):
        with MujocoBackend(scene, 1) as single:
            single.reset(xy[i:i + 1], quat[i:i + 1])
            for ctrl in controls:
                alone = single.step(ctrl[i:i + 1])
        np.testing.assert_array_equal(alone.qpos[0], together.qpos[i])
        np.testing.assert_array_equal(alone.qvel[0], together.qvel[i])
        np.testing.assert_array_equal(alone.contact_force[0], together.contact_force[i])


def test_only_the_chosen_rows_are_stepped(scene):
    """`step(ctrl, rows)` steps the chosen environments exactly as a full step would and leaves the others as they
    were (the evaluator and the oracle's rollouts stop simulating scenes whose episode has ended)."""
    batch, steps = 4, 10
    xy, quat = _placements(batch, seed=1)
    controls = moving_controls(batch, steps, seed=2)
    rows = np.array([True, False, True, False])
    with MujocoBackend(scene, batch, num_threads=2) as full, MujocoBackend(scene, batch, num_threads=2) as some:
        start = full.reset(xy, quat).qpos.copy()
        some.reset(xy, quat)
        for ctrl in controls:
            everyone = full.step(ctrl)
            chosen = some.step(ctrl, rows)
        np.testing.assert_array_equal(chosen.qpos[rows], everyone.qpos[rows])
        np.testing.assert_array_equal(chosen.qpos[~rows], start[~rows])
        assert some.datas[1].time == some.datas[3].time < some.datas[0].time


def test_state_shapes_and_poses_agree_with_qpos(scene):
    with MujocoBackend(scene, 3) as backend:
        state = backend.reset()
    m = scene.model
    rows = body_rows(m.nbody)
    assert state.qpos.shape == (3, m.nq) and state.body_pos.shape == (3, rows, 3) and rows % 8 == 0
    # Padding rows past the model's bodies hold the origin and the identity rotation.
    assert (state.body_pos[:, m.nbody:] == 0).all() and (state.body_quat[:, m.nbody:] == [1, 0, 0, 0]).all()
    assert state.contact_pos.shape == (3, 2, 8, 3) and state.contact_geom.dtype == np.int32
    adr = scene.object_qpos_adr  # poses come from the last substep's forward pass, one 5 ms step behind qpos
    np.testing.assert_allclose(state.object_pos, state.qpos[:, adr:adr + 3], atol=1e-6)
    np.testing.assert_allclose(state.object_quat, state.qpos[:, adr + 3:adr + 7], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(state.tcp_quat, axis=1), 1.0)
    np.testing.assert_allclose(state.gripper_width, 0.08)
    assert (state.contact_geom == -1).all() and (state.contact_force == 0).all()  # open gripper touches nothing


def test_host_state_travels_to_jit_as_one_block(scene):
    import jax

    from partinstruct_mjx.sim.state import HostBlock, unpacked

    with MujocoBackend(scene, 2) as backend:
        state = backend.reset(*_placements(2))
        for _ in range(10):  # the fingers close: the finger fields change from their reset values
            state = backend.step(np.tile(np.r_[panda.HOME_ARM_QPOS, panda.FINGER_CLOSED], (2, 1)))
    block = state.for_jit()
    assert isinstance(block, HostBlock) and block.floats.dtype == np.float32
    restored = jax.jit(unpacked)(block)
    assert restored.qpos is None and restored.qvel is None
    for name in ("time", "arm_qpos", "finger_qpos", "tcp_pos", "tcp_quat", "object_pos", "object_quat", "body_pos",
                 "body_quat", "contact_pos", "contact_force", "contact_geom"):
        original = getattr(state, name)
        np.testing.assert_array_equal(np.asarray(getattr(restored, name)), original.astype(np.asarray(
            getattr(restored, name)).dtype), err_msg=name)


def test_physics_state_round_trip_replays_exactly(scene):
    controls = moving_controls(2, 20, seed=3)
    with MujocoBackend(scene, 2) as backend:
        backend.reset()
        saved = backend.get_physics_state()
        first = [backend.step(c).qpos.copy() for c in controls]
        backend.set_physics_state(saved)
        second = [backend.step(c).qpos.copy() for c in controls]
    np.testing.assert_array_equal(np.array(first), np.array(second))


def test_physics_steps_split_only_while_a_pad_touches(scene):
    """`contact_split` halves the physics step while a finger pad has a contact, and only then: the arm sweeping in
    free space moves exactly as without it; a scripted pick of the object ends elsewhere."""
    from dataclasses import replace

    def run(split, controls, xy=None):
        with MujocoBackend(replace(scene, config=replace(scene.config, contact_split=split)), 1) as backend:
            backend.reset(xy)
            return np.array([backend.step(c).qpos.copy() for c in controls]), backend

    free = moving_controls(1, 30, seed=1)
    plain, _ = run(1, free)
    split, backend = run(2, free)
    np.testing.assert_array_equal(plain, split)
    assert backend._fine_model.opt.timestep == scene.config.timestep / 2
    picks = []
    for split in (1, 2):
        with MujocoBackend(replace(scene, config=replace(scene.config, contact_split=split)), 1) as backend:
            picks.append(run_pick(backend, backend.reset(), PickConfig(hold_steps=1)).final_state.qpos.copy())
    assert np.abs(picks[0] - picks[1]).max() > 1e-6
    with pytest.raises(SceneError, match="contact_split"):
        replace(scene.config, contact_split=0)


def test_bad_inputs_raise_clear_errors(scene):
    with pytest.raises(SceneError, match="batch_size"):
        MujocoBackend(scene, 0)
    with MujocoBackend(scene, 2) as backend:
        backend.reset()
        with pytest.raises(SceneError, match=r"ctrl must have shape \(2, 8\)"):
            backend.step(np.zeros((3, 8)))
        with pytest.raises(SceneError, match="physics states"):
            backend.set_physics_state(np.zeros((2, 5)))
