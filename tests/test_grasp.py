"""A closed gripper squeezing an object lifts it and holds it for 3 s (scripted top-down picks)."""

import numpy as np

from partinstruct_mjx.control.scripted_pick import PickConfig, run_pick
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from tests.test_mujoco_backend import _placements


def test_scripted_pick_lifts_and_holds_for_three_seconds(scene):
    batch = 8
    xy, quat = _placements(batch, seed=4)
    config = PickConfig()
    assert config.hold_steps * scene.config.control_dt == 3.0
    with MujocoBackend(scene, batch) as backend:
        result = run_pick(backend, backend.reset(xy, quat), config)
    assert (result.ik_error < 1e-3).all()
    np.testing.assert_array_less(0.12, result.lift)          # lifted ~15 cm
    np.testing.assert_array_less(result.hold_drift, 0.005)   # did not slip during the 3 s hold
    np.testing.assert_array_less(20.0, result.grip_force)    # both fingers squeezing the whole time
    width = result.final_state.gripper_width
    np.testing.assert_array_less(0.045, width)               # pads on the 5 cm block, < 2.5 mm penetration each
    touched = result.final_state.contact_geom
    assert np.isin(touched[touched >= 0], scene.object_geoms).all()
