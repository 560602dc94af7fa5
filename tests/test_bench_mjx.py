"""The mjx bench suite (collision-budget variants, rows, markdown, the CLI end to end), the benchmarks' JSON data files
and the env-steps-vs-batch plot drawn from them."""

import copy
import itertools
import json

import numpy as np
import pytest

from partinstruct_mjx import paths
from partinstruct_mjx.bench import mjx_env
from partinstruct_mjx.bench.report import data_path, env_row, read_data, write_report
from partinstruct_mjx.bench.timing import Throughput
from partinstruct_mjx.sim import panda
from partinstruct_mjx.tasks.task_types import task_type

MUG = paths.assets_root() / "objects/mug/mug_000/object.xml"
INFO = {"date": "2026-01-01 00:00 UTC", "git_sha": "abc1234", "machine": "test machine", "versions": {"python": "3"}}


@pytest.fixture(scope="module")
def mug_scene():
    return mjx_env.object_scene(MUG)


def _colliding_kinds(scene, model) -> set[tuple[str, str]]:
    """Kinds of geom pairs that MuJoCo's contype/conaffinity filter lets collide (bodies apart)."""
    def kind(g):
        if g == scene.table_geom:
            return "table"
        if scene.geom_part[g] >= 0:
            return "object"
        if scene.geom_finger[g] >= 0:
            return "pad"
        return "hand" if model.geom_bodyid[g] == scene.hand_body else "arm"

    ct, ca = model.geom_contype, model.geom_conaffinity
    geoms = np.flatnonzero((ct > 0) | (ca > 0))
    return {tuple(sorted((kind(i), kind(j)))) for i, j in itertools.combinations(geoms, 2)
            if model.geom_bodyid[i] != model.geom_bodyid[j] and (ct[i] & ca[j] or ct[j] & ca[i])}


def test_variants_change_only_what_collides_or_the_solver_caps(mug_scene):
    built = _colliding_kinds(mug_scene, mug_scene.model)
    assert built == {("arm", "table"), ("hand", "table"), ("hand", "object"), ("pad", "table"), ("object", "pad"),
                     ("object", "table")}
    expected = {"pads-object and object-table only": {("object", "pad"), ("object", "table")},
                "as built, half of the object's hulls collide": built,
                "object-table only": {("object", "table")},
                "as built, line search 4 iterations": built,
                "as built, line search 4, 1 Newton iteration": built}
    solver = {"as built, line search 4 iterations": (mug_scene.model.opt.iterations, 4),
              "as built, line search 4, 1 Newton iteration": (1, 4)}
    assert [v.name for v in mjx_env.VARIANTS] == list(expected)
    hulls = mug_scene.object_geoms
    for variant in mjx_env.VARIANTS:
        model = copy.deepcopy(mug_scene.model)
        variant.edit(mug_scene, model)
        assert _colliding_kinds(mug_scene, model) == expected[variant.name], variant.name
        colliding = np.count_nonzero(model.geom_contype[hulls])
        assert colliding == (len(hulls) + 1) // 2 if "half" in variant.name else colliding == len(hulls)
        assert np.array_equal(model.geom_size, mug_scene.model.geom_size)
        caps = (model.opt.iterations, model.opt.ls_iterations)
        assert caps == solver.get(variant.name, (mug_scene.model.opt.iterations, mug_scene.model.opt.ls_iterations))
    assert np.array_equal(mug_scene.model.geom_contype, mjx_env.object_scene(MUG).model.geom_contype)  # copies only


def test_bench_episodes_and_circling_actions(mug_scene):
    episodes = mjx_env.bench_episodes(mug_scene)
    assert len(episodes) == mjx_env.EPISODES
    assert {(e.obj_class, e.obj_id) for e in episodes} == {("mug", "mug_000")}
    assert task_type(3).slots(episodes[0].chain) == ({"P1": mug_scene.part_names[0]}, {"D1": "left"})
    assert len({e.obj_pose for e in episodes}) == mjx_env.EPISODES
    tcp = np.tile([1.0, 0.0, 0.0, 0.0, 0.0, 0.1, 0.3], (3, 1))  # [qx, qy, qz, qw, x, y, z]
    actions = np.asarray(mjx_env.circling_actions(tcp, mjx_env.GRIPPER_PERIOD))
    assert actions.shape == (mjx_env.GRIPPER_PERIOD, 3, 7)
    offset = np.linalg.norm(actions[..., :2] - tcp[None, :, 4:6], axis=-1)
    np.testing.assert_allclose(offset, mjx_env.CIRCLE_RADIUS, atol=1e-6)
    np.testing.assert_allclose(actions[..., 2], 0.3)
    assert set(np.unique(actions[..., 6])) == {np.float32(panda.FINGER_CLOSED), np.float32(panda.FINGER_OPEN)}


def _results(per_s_4096=120_000.0, compile_s=20.0) -> mjx_env.MjxBenchResults:
    results = mjx_env.MjxBenchResults("NVIDIA H100 80GB HBM3", 20, 5, 10, 20, 20, 10)
    for batch, per_s in ((1024, 50_000.0), (4096, per_s_4096)):
        results.rows.append(mjx_env.Row("103619", mjx_env.AS_BUILT, "jax", batch, 16, 248,
                                        Throughput(compile_s, per_s, (0.9 * per_s, 1.1 * per_s)), 15.0))
    results.rows.append(mjx_env.Row("103619", mjx_env.VARIANTS[0].name, "jax", 4096, 16, 96,
                                    Throughput(18.0, 200_000.0, (190_000.0, 210_000.0)), 12.0))
    results.rows.append(mjx_env.Row("103619", mjx_env.AS_BUILT, "warp", 4096, 16, None, None, note="not installed (x)"))
    return results


def test_markdown_rows_and_target():
    text = mjx_env.markdown(_results())
    assert "| 103619 | jax | 16 | 248 | 4,096 | 120,000 | 108,000 - 132,000 | 20.00 | 15.0 |" in text
    assert "Collision and solver budget, `103619` at batch 4,096" in text
    assert "| pads-object and object-table only | jax | 16 | 96 | 200,000 |" in text
    assert "| 103619 | warp | 16 | - | 4,096 | not installed (x) | - | - | - |" in text
    assert "`103619` (jax) 120,000 env steps/s, compile 20.0 s (step) + 15.0 s (reset): met" in text
    assert "compile 50.0 s (step) + 15.0 s (reset): not met" in mjx_env.markdown(_results(compile_s=50.0))
    assert "not met" in mjx_env.markdown(_results(per_s_4096=90_000.0))
    rows = mjx_env.data_rows(_results())
    assert [r["series"] is not None for r in rows] == [True, True, False, False]
    assert rows[0]["series"] == "MJX (jax) on NVIDIA H100 80GB HBM3, Panda + 103619 (16 hulls)"
    assert rows[3]["env_steps_per_s"] is None and rows[3]["note"] == "not installed (x)"
    json.dumps(rows)  # plain data


def test_warp_row_says_not_installed_when_warp_is_missing():
    from mujoco.mjx import warp as mjx_warp

    if mjx_warp.WARP_INSTALLED:
        pytest.skip("warp-lang is installed here")
    [row] = mjx_env.measure_warp(MUG, (256, 4096), 20, 5)
    assert row.impl == "warp" and row.timing is None and row.note.startswith("not installed")


def test_report_data_round_trip(tmp_path):
    report = tmp_path / "benchmarks.md"
    rows = [env_row("series a", 8, 1234.5, (1000.0, 1300.0), threads=2), env_row(None, 16, None, (None, None))]
    write_report(report, "suite_x", "Suite X", "| a |\n", INFO, "partinstruct bench x", rows)
    write_report(report, "suite_y", "Suite Y", "| b |\n", INFO, "partinstruct bench y")
    assert data_path(report, "suite_x") == tmp_path / "bench_data" / "suite_x.json"
    data = read_data(tmp_path / "bench_data")
    assert list(data) == ["suite_x"]  # a suite without rows writes no data file
    assert data["suite_x"]["rows"] == json.loads(json.dumps(rows))
    assert data["suite_x"]["provenance"] == INFO and data["suite_x"]["command"] == "partinstruct bench x"
    text = report.read_text()
    assert "<!-- bench:suite_x -->\n## Suite X\n\n- command: `partinstruct bench x`" in text and "| b |" in text
    assert read_data(tmp_path / "missing") == {}


def test_plot_is_drawn_from_the_data_files(tmp_path):
    pytest.importorskip("matplotlib")
    from partinstruct_mjx.bench import plot

    report = tmp_path / "benchmarks.md"
    cpu = [env_row("CPU env", b, r, (r - 70, r + 70)) for b, r in ((8, 1200.0), (1, 700.0))]
    write_report(report, "cpu", "CPU", "t\n", INFO, "c", cpu)
    write_report(report, "mjx_gpu", "MJX", "t\n", INFO, "c", mjx_env.data_rows(_results()))
    lines = plot.series(read_data(tmp_path / "bench_data"))
    assert lines["CPU env"] == [(1, 700.0, 630.0, 770.0), (8, 1200.0, 1130.0, 1270.0)]
    assert len(lines) == 2  # variant and unmeasured rows carry no series
    out = plot.plot(tmp_path / "bench_data", tmp_path / "plot.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot.main(["--data", str(tmp_path / "empty"), "--output", str(tmp_path / "x.png")]) == 2


@pytest.mark.slow
def test_mjx_suite_end_to_end_on_cpu(tmp_path, monkeypatch, capsys, mug_scene):
    """`partinstruct bench mjx` with batch 2 and 2 steps (one variant to keep it short): section, data, plot."""
    pytest.importorskip("brax")
    from partinstruct_mjx.cli import main

    object_table = [v for v in mjx_env.VARIANTS if v.name == "object-table only"]
    assert len(object_table) == 1
    monkeypatch.setattr(mjx_env, "VARIANTS", tuple(object_table))
    report = tmp_path / "benchmarks.md"
    assert main(["bench", "mjx", "--object", str(MUG), "--batch-sizes", "2", "--steps", "2", "--repeats", "1",
                 "--output", str(report)]) == 0
    text = report.read_text()
    assert "<!-- bench:mjx_cpu -->" in text and "## MJX env steps (impl jax, warp, CPU)" in text
    hulls = len(mug_scene.object_geoms)
    assert f"| mug_000 | jax | {hulls} |" in text and f"| object-table only | jax | {hulls} |" in text
    assert "Target not assessed: batch 4,096 was not measured." in text
    rows = read_data(tmp_path / "bench_data")["mjx_cpu"]["rows"]
    assert [(r["variant"], r["impl"]) for r in rows] == [(mjx_env.AS_BUILT, "jax"), ("object-table only", "jax"),
                                                         (mjx_env.AS_BUILT, "warp")]
    assert rows[0]["env_steps_per_s"] > 0 and rows[0]["compile_s"] > 0 and rows[1]["contacts"] < rows[0]["contacts"]
    pytest.importorskip("matplotlib")
    from partinstruct_mjx.bench import plot

    assert plot.plot(tmp_path / "bench_data", tmp_path / "plot.png").exists()


def test_warp_only_run_writes_its_own_section(tmp_path, mug_scene):
    """`--impls warp` measures no JAX rows and writes a section of its own (here without warp-lang or a GPU: the
    row says why it was not measured)."""
    from mujoco.mjx import warp as mjx_warp

    from partinstruct_mjx.cli import main

    if mjx_warp.WARP_INSTALLED:
        pytest.skip("warp-lang is installed here")
    report = tmp_path / "benchmarks.md"
    assert main(["bench", "mjx", "--impls", "warp", "--object", str(MUG), "--batch-sizes", "4096", "--output",
                 str(report)]) == 0
    text = report.read_text()
    assert "<!-- bench:mjx_cpu_warp -->" in text and "## MJX env steps (impl warp, CPU)" in text
    hulls = len(mug_scene.object_geoms)
    assert f"| mug_000 | warp | {hulls} | - | 4,096 | not installed" in text and "| jax |" not in text
