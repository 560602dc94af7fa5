"""Shared fixtures: one compiled scene per session (compiling is the slow part of most tests)."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; must be set before MuJoCo is imported

import pytest  # noqa: E402

from partinstruct_mjx.sim.scene import SceneConfig, build_scene  # noqa: E402


@pytest.fixture(scope="session")
def scene():
    return build_scene(SceneConfig())
