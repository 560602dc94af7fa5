"""Shared fixtures: one compiled scene per session (compiling is the slow part of most tests)."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; must be set before MuJoCo is imported

import pytest  # noqa: E402

from partinstruct_mjx.sim.scene import SceneConfig, build_scene  # noqa: E402


@pytest.fixture(scope="session")
def scene():
    return build_scene(SceneConfig())


@pytest.fixture
def command_help(capsys):
    """`partinstruct <command> --help`'s text (it must exit 0)."""
    from partinstruct_mjx.cli import main

    def run(command: str) -> str:
        with pytest.raises(SystemExit) as exit_info:
            main([command, "--help"])
        assert exit_info.value.code == 0
        return capsys.readouterr().out

    return run
