"""Shared fixtures: one compiled scene per session (compiling is the slow part of most tests)."""

import pytest

from partinstruct_mjx.sim.scene import SceneConfig, build_scene


@pytest.fixture(scope="session")
def scene():
    return build_scene(SceneConfig())
