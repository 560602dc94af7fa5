"""Reference inverse kinematics with mink (a QP per iteration, joint limits respected) for the TCP site."""

from __future__ import annotations

from dataclasses import dataclass

import mink
import mujoco
import numpy as np

from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.scene import Scene


@dataclass(frozen=True)
class MinkIKConfig:
    """Iteration budget and tolerances of the reference IK (step counts, never wall-clock time)."""

    max_iterations: int = 300
    dt: float = 0.05
    position_tolerance: float = 1e-4
    rotation_tolerance: float = 1e-3
    posture_cost: float = 1e-3
    damping: float = 1e-4


@dataclass(frozen=True)
class IKSolution:
    arm_qpos: np.ndarray
    position_error: float
    rotation_error: float
    converged: bool


class MinkIK:
    """Solves TCP pose targets for the Panda of a scene, starting from a given arm configuration."""

    def __init__(self, scene: Scene, config: MinkIKConfig = MinkIKConfig()):
        self.scene = scene
        self.config = config
        self._configuration = mink.Configuration(scene.model)
        self._frame_task = mink.FrameTask(panda.TCP_SITE, "site", position_cost=1.0, orientation_cost=1.0)
        self._posture_task = mink.PostureTask(scene.model, cost=config.posture_cost)
        self._limits = [mink.ConfigurationLimit(scene.model)]

    def solve(self, arm_qpos_init: np.ndarray, tcp_pos: np.ndarray, tcp_quat: np.ndarray) -> IKSolution:
        """Arm joint angles putting the TCP at `tcp_pos` with orientation `tcp_quat` (w, x, y, z)."""
        scene, cfg = self.scene, self.config
        q = scene.model.qpos0.copy()
        q[scene.arm_qpos_adr] = arm_qpos_init
        q[scene.finger_qpos_adr] = panda.FINGER_OPEN
        self._configuration.update(q)
        self._posture_task.set_target(q)
        target = mink.SE3.from_rotation_and_translation(mink.SO3(np.asarray(tcp_quat, float)), np.asarray(tcp_pos, float))
        self._frame_task.set_target(target)
        tasks = [self._frame_task, self._posture_task]
        for _ in range(cfg.max_iterations):
            error = self._frame_task.compute_error(self._configuration)
            if np.linalg.norm(error[:3]) < cfg.position_tolerance and np.linalg.norm(error[3:]) < cfg.rotation_tolerance:
                break
            velocity = mink.solve_ik(self._configuration, tasks, cfg.dt, solver="daqp", damping=cfg.damping,
                                     limits=self._limits)
            self._configuration.integrate_inplace(velocity, cfg.dt)
        error = self._frame_task.compute_error(self._configuration)
        pos_err, rot_err = float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:]))
        return IKSolution(
            arm_qpos=self._configuration.q[scene.arm_qpos_adr].copy(),
            position_error=pos_err,
            rotation_error=rot_err,
            converged=pos_err < cfg.position_tolerance * 10 and rot_err < cfg.rotation_tolerance * 10,
        )


def tcp_pose_of(scene: Scene, arm_qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics: TCP position and (w, x, y, z) orientation for arm joint angles."""
    data = mujoco.MjData(scene.model)
    data.qpos[scene.arm_qpos_adr] = arm_qpos
    mujoco.mj_kinematics(scene.model, data)
    return data.site_xpos[scene.tcp_site].copy(), data.xquat[scene.hand_body].copy()
