"""The mjx backend's row operations that streaming and backtracking use: reset some scenes, restore some scenes
from a snapshot, the others untouched. JAX's MJX on the CPU compiles its step for about a minute, so this is slow."""

import numpy as np
import pytest

from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mjx_backend import MjxBackend

pytestmark = pytest.mark.slow


def test_reset_and_restore_touch_only_the_chosen_rows(scene):
    backend = MjxBackend(scene, 2)
    backend.reset(np.array([[0.05, 0.10], [-0.05, 0.15]]))
    ctrl = np.tile(panda.HOME_CTRL, (2, 1))
    ctrl[:, 0] += 0.3
    snapshot = backend.snapshot()
    moved = backend.step(ctrl)
    moved_arm = np.asarray(moved.arm_qpos).copy()
    restored = backend.restore(snapshot, np.array([True, False]))
    np.testing.assert_array_equal(np.asarray(restored.arm_qpos[0]), np.asarray(snapshot.qpos[0, :7]))
    np.testing.assert_array_equal(np.asarray(restored.arm_qpos[1]), moved_arm[1])
    fresh = backend.reset(np.array([[0.0, 0.0], [0.10, -0.10]]), rows=np.array([False, True]))
    np.testing.assert_allclose(np.asarray(fresh.object_pos[1, :2]), [0.10, -0.10], atol=0.01)
    np.testing.assert_array_equal(np.asarray(fresh.arm_qpos[0]), np.asarray(restored.arm_qpos[0]))
