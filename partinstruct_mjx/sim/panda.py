"""Panda constants shared by the scene, the backends and the controllers (spec sections 1.2, 1.3 and 1.6)."""

import jax.numpy as jnp
import numpy as np

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
FINGER_BODIES = ("panda_leftfinger", "panda_rightfinger")
HAND_BODY = "panda_hand"
TCP_SITE = "tcp"
GRASPTARGET_SITE = "grasptarget"
FINGERTIP_SITE = "fingertip"
GRIPPER_ACTUATOR = "gripper"

BASE_POS = np.array([0.6, 0.0, 0.05])
HOME_ARM_QPOS = np.array([0.920, 0.286, 0.713, -1.963, -0.051, 2.042, -0.164])
FINGER_OPEN = 0.04
FINGER_CLOSED = 0.0
HOME_CTRL = np.concatenate([HOME_ARM_QPOS, [FINGER_OPEN]])
"""Actuator targets at home: seven arm joint angles, then the per-finger opening in metres."""

GRIPPER_GAIN = 4125.0
GRIPPER_BIAS = (-45.0, -3000.0)
"""The gripper actuator's gain and its bias (constant, per metre of opening); assets_mjcf/robots/panda/panda.xml."""


def finger_ctrl(opening):
    """Gripper control at which the unloaded fingers settle `opening` (m per finger) from the middle.

    The actuator aims 15 mm past closed at control 0 (the squeeze), so between the ends a control is not an
    opening: a control of 0.016 holds the fingers 6 mm from the middle. FINGER_OPEN maps to itself.
    """
    return jnp.clip((opening * -GRIPPER_BIAS[1] - GRIPPER_BIAS[0]) / GRIPPER_GAIN, FINGER_CLOSED, FINGER_OPEN)


NUM_ARM_JOINTS = 7
NUM_CTRL = 8
