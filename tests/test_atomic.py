"""Atomic output: the target changes only when writing completes, and a failure leaves nothing behind."""

import pytest

from partinstruct_mjx.atomic import atomic_path, atomic_write


def test_complete_write_replaces_the_file(tmp_path):
    target = tmp_path / "sub" / "data.json"
    with atomic_write(target) as file:
        file.write("new")
        assert not target.exists()  # nothing visible until the block ends
    assert target.read_text() == "new" and sorted(p.name for p in target.parent.iterdir()) == ["data.json"]


@pytest.mark.parametrize("writer", ["file", "path"])
def test_failed_write_keeps_the_old_file_and_no_temporary(tmp_path, writer):
    target = tmp_path / "video.mp4"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        if writer == "file":
            with atomic_write(target) as file:
                file.write("half")
                raise RuntimeError("interrupted")
        else:
            with atomic_path(target) as temporary:
                assert temporary.suffix == ".mp4" and temporary.parent == tmp_path
                temporary.write_text("half")
                raise RuntimeError("interrupted")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["video.mp4"]
