"""The oracle's skill kinds: how the machine and its planners number the five base skills."""

GRASP, TOUCH, MOVE, ROTATE, RELEASE = range(5)
SKILL_KINDS = {"grasp_obj": GRASP, "touch_obj": TOUCH, "move_gripper": MOVE, "rotate_obj": ROTATE,
               "release_obj": RELEASE}
