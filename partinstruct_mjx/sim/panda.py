"""Panda constants shared by the scene, the backends and the controllers (spec sections 1.2, 1.3 and 1.6)."""

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

NUM_ARM_JOINTS = 7
NUM_CTRL = 8
