"""A scripted top-down pick-and-lift in joint space, planned with the mink reference IK.

It is the project's smoke test of the whole physics stack (reach, squeeze, lift, hold) and the `simulate`
command's episode until the oracle exists. Joint targets are interpolated linearly between IK waypoints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from partinstruct_mjx.control.mink_ik import MinkIK
from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend, object_z_range
from partinstruct_mjx.sim.state import SceneState

TOP_CLEARANCE = 0.014
"""Distance from the TCP down to the object's top at the grasp: the pads then cover 0.8-4.2 cm below the top."""


@dataclass(frozen=True)
class PickConfig:
    """Waypoints and durations (control steps at 20 Hz) of the scripted pick."""

    approach_height: float = 0.10
    lift_height: float = 0.15
    reach_steps: int = 40
    descend_steps: int = 30
    close_steps: int = 20
    lift_steps: int = 40
    hold_steps: int = 60


@dataclass(frozen=True)
class PickResult:
    """Per-environment outcome of a scripted pick (arrays of length B)."""

    lift: np.ndarray
    """Object height gain at the end of the hold, metres."""
    hold_drift: np.ndarray
    """Largest object height change during the hold, metres."""
    grip_force: np.ndarray
    """Smallest per-finger total normal force during the hold, newtons."""
    ik_error: np.ndarray
    """Largest TCP position error among the IK waypoints, metres."""
    final_state: SceneState

    @property
    def success(self) -> np.ndarray:
        return (self.lift > 0.1) & (self.hold_drift < 0.01) & (self.grip_force > 20.0)


def top_down_quat(yaw: float) -> np.ndarray:
    """TCP orientation (w, x, y, z) with the approach axis pointing down and the fingers closing along `yaw`."""
    y_axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    z_axis = np.array([0.0, 0.0, -1.0])
    xyzw = Rotation.from_matrix(np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis])).as_quat()
    return np.roll(xyzw, 1)


def plan_pick(backend: MujocoBackend, ik: MinkIK, state: SceneState, config: PickConfig) -> tuple[np.ndarray, np.ndarray]:
    """Joint-space control sequences (B, T, 8) for a top-down pick of each environment's object.

    Returns the controls and the worst IK position error per environment.
    """
    controls, errors = [], []
    for i, data in enumerate(backend.datas):
        _, top = object_z_range(backend.scene, data)
        grasp = np.array([*state.object_pos[i, :2], top + TOP_CLEARANCE])
        object_yaw = Rotation.from_quat(np.roll(state.object_quat[i], -1)).as_euler("xyz")[2]
        best = None
        for k in range(4):
            quat = top_down_quat(object_yaw + k * np.pi / 2)
            waypoints, worst = [panda.HOME_ARM_QPOS], 0.0
            for offset in (config.approach_height, 0.0, config.lift_height):
                solution = ik.solve(waypoints[-1], grasp + [0.0, 0.0, offset], quat)
                waypoints.append(solution.arm_qpos)
                worst = max(worst, solution.position_error)
            travel = sum(np.abs(b - a).sum() for a, b in zip(waypoints, waypoints[1:]))
            if best is None or (worst, travel) < (best[1] + 1e-3, best[2]):
                best = (waypoints, worst, travel)
        controls.append(_interpolate(best[0], config))
        errors.append(best[1])
    return np.stack(controls), np.array(errors)


def _interpolate(waypoints: list[np.ndarray], config: PickConfig) -> np.ndarray:
    home, pregrasp, grasp, lifted = waypoints
    open_, closed = panda.FINGER_OPEN, panda.FINGER_CLOSED

    def ramp(a, b, steps, finger):
        t = np.linspace(1.0 / steps, 1.0, steps)[:, None]
        arm = a + t * (b - a)
        return np.hstack([arm, np.full((steps, 1), finger)])

    return np.concatenate([
        ramp(home, pregrasp, config.reach_steps, open_),
        ramp(pregrasp, grasp, config.descend_steps, open_),
        ramp(grasp, grasp, config.close_steps, closed),
        ramp(grasp, lifted, config.lift_steps, closed),
        ramp(lifted, lifted, config.hold_steps, closed),
    ])


def run_pick(backend: MujocoBackend, state: SceneState, config: PickConfig = PickConfig()) -> PickResult:
    """Plan and execute the pick on every environment of `backend`, starting from `state` (after reset)."""
    ik = MinkIK(backend.scene)
    controls, ik_error = plan_pick(backend, ik, state, config)
    if controls.shape[1] <= config.hold_steps:
        raise SceneError("the pick plan is shorter than its hold phase")
    start_z = state.object_pos[:, 2].copy()
    hold_start = controls.shape[1] - config.hold_steps
    hold_z, hold_force = [], []
    for t in range(controls.shape[1]):
        state = backend.step(controls[:, t])
        if t >= hold_start:
            hold_z.append(state.object_pos[:, 2].copy())
            hold_force.append(state.contact_force.sum(axis=-1).min(axis=-1))
    hold_z = np.array(hold_z)
    return PickResult(
        lift=state.object_pos[:, 2] - start_z,
        hold_drift=np.abs(hold_z - hold_z[0]).max(axis=0),
        grip_force=np.array(hold_force).min(axis=0),
        ik_error=ik_error,
        final_state=state,
    )
