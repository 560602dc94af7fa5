"""Policy training on real oracle demos: windows, normalisation, instruction cache, overfitting, resume, CLI, acting."""

import json
from collections import Counter
from dataclasses import replace

import jax
import numpy as np
import pytest

from partinstruct_mjx.assets.catalog import load_catalog
from partinstruct_mjx.cli import main
from partinstruct_mjx.data.demos import read_demos
from partinstruct_mjx.errors import DataError
from partinstruct_mjx.jax_setup import enable_compilation_cache
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.tasks.episodes import generate_episodes, read_metadata, write_metadata
from partinstruct_mjx.train import checkpoints, features, language
from partinstruct_mjx.train.config import ModelConfig, TrainConfig
from partinstruct_mjx.train.dataset import Normalizer, WindowSampler, load_demos, split_episodes
from partinstruct_mjx.train.model import DP3Policy
from partinstruct_mjx.train.trainer import example_inputs, train

TINY = ModelConfig(encoder_dims=(16,), feature_dim=32, step_embed_dim=32, down_dims=(32,), groups=8)
TINY_ARGS = ["--down-dims", "32", "--encoder-dims", "16", "--feature-dim", "32"]


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    """Two oracle demos of one bottle (a grasp and a touch), synthesized by `partinstruct demos`."""
    enable_compilation_cache()
    root = assets_root()
    episodes = generate_episodes([e for e in load_catalog(root) if e["category"] == "bottle"], root, seed=0,
                                 per_type=12, splits=("train",))
    count = Counter((e.obj_id, e.task_type) for e in episodes)
    obj_id = max(sorted({e.obj_id for e in episodes}), key=lambda o: min(count[o, 1], count[o, 2]))
    chosen = [next(e for e in episodes if e.obj_id == obj_id and e.task_type == t) for t in (1, 2)]
    out = tmp_path_factory.mktemp("train_demos")
    write_metadata(chosen, out / "episodes.json")
    assert main(["demos", "--metadata", str(out / "episodes.json"), "--batch-size", "2", "--out",
                 str(out / "demos"), "--quiet"]) == 0
    summary = json.loads((out / "demos" / "summary.json").read_text())
    assert summary["successes"] == 2, f"the oracle failed an episode: {summary['per_task_type']}"
    return out / "demos"


def tiny_config(demo_dir, out, **changes) -> TrainConfig:
    settings = dict(steps=12, batch_size=8, lr=3e-3, val_every=6, log_every=2, model=TINY)
    return TrainConfig(data=str(demo_dir), policy="dp3s", out=str(out), **{**settings, **changes})


@pytest.fixture(scope="module")
def cli_run(demo_dir, tmp_path_factory):
    """A run of `partinstruct train` with a tiny network: (run directory, its arguments, its output)."""
    run = tmp_path_factory.mktemp("train_cli") / "run"
    args = ["train", "--data", str(demo_dir), "--policy", "dp3s", "--out", str(run), "--steps", "4", "--batch-size",
            "8", "--val-every", "2", "--quiet", *TINY_ARGS]
    return run, args


def test_windows_pad_like_diffusion_policy_and_cover_every_step(demo_dir):
    data = load_demos(demo_dir, "agentview_part_pcd")
    raw = [demo for _, demo in read_demos(demo_dir / "data" / "bottle.hdf5")]
    lengths = [len(demo["actions"]) for demo in raw]
    assert data.episode_ends.tolist() == np.cumsum(lengths).tolist() and data.sampler == "stride"
    assert data.clouds.shape == (sum(lengths), 1024, 4)
    assert sorted(data.instructions) == sorted({t.decode() for d in raw for t in d["skill_instructions"]})
    xyz = load_demos(demo_dir, "agentview_pcd")
    np.testing.assert_array_equal(xyz.clouds, data.clouds[..., :3])

    model = ModelConfig()
    vectors = np.eye(len(data.instructions), language.EMBEDDING_DIM, dtype=np.float32)
    normalizer = Normalizer.fit(data.actions, data.proprio)
    sampler = WindowSampler(data, np.arange(2), normalizer, vectors, model, batch_size=8, seed=0)
    # horizon 16, 1 step of padding before (2 observation steps), 7 after (8 action steps): L - 7 windows per demo
    assert len(sampler) == sum(length - 7 for length in lengths)
    first, last = sampler.steps(np.array([0, lengths[0] - 8]))
    assert first.tolist() == [0] + list(range(15))
    assert last.tolist() == list(range(lengths[0] - 9, lengths[0])) + [lengths[0] - 1] * 7
    second = sampler.steps(np.array([lengths[0] - 7]))[0]
    assert second.tolist() == [lengths[0]] + list(range(lengths[0], lengths[0] + 15)), "windows cross demos"

    batch = sampler.batch(3)
    assert {k: v.shape for k, v in batch.items()} == {"clouds": (8, 2, 1024, 4), "proprio": (8, 2, 17),
                                                     "instruction": (8, 256), "actions": (8, 16, 10)}
    assert all(v.dtype == np.float32 for v in batch.values())
    assert np.abs(batch["actions"]).max() <= 1 + 1e-6 and np.abs(batch["proprio"]).max() <= 1 + 1e-6
    windows = sampler.windows(3)
    steps = sampler.steps(windows)
    np.testing.assert_array_equal(batch["clouds"], data.clouds[steps[:, :2]].astype(np.float32))
    np.testing.assert_array_equal(batch["instruction"], vectors[data.instruction_ids[steps[:, 1]]])
    np.testing.assert_allclose(normalizer.actions_back(batch["actions"]), data.actions[steps], atol=1e-5)
    # an epoch visits every window once, and batch k is the same whenever it is asked for
    epoch = np.concatenate([sampler.windows(k) for k in range(len(sampler) // 8)])
    assert len(set(epoch.tolist())) == len(epoch)
    np.testing.assert_array_equal(sampler.windows(3), windows)


def test_network_actions_and_proprio_round_trip(demo_dir):
    demo = next(d for _, d in read_demos(demo_dir / "data" / "bottle.hdf5"))
    # a top-down grasp's roll wraps at pi: the demo's actions, and the same actions with rolls alternating across pi
    wrapped = demo["actions"].copy()
    wrapped[:, 3] = np.where(np.arange(len(wrapped)) % 2, np.pi - 0.05, 0.05 - np.pi)
    actions = np.concatenate([demo["actions"], wrapped])
    back = np.asarray(features.actions_from_model(features.actions_to_model(actions)))
    np.testing.assert_allclose(back[:, [0, 1, 2, 6]], actions[:, [0, 1, 2, 6]], atol=1e-6)
    np.testing.assert_allclose(np.angle(np.exp(1j * (back[:, 3:6] - actions[:, 3:6]))), 0, atol=1e-4)
    across = np.asarray(features.actions_to_model(wrapped[:2]))
    assert np.abs(across[0] - across[1]).max() < 0.2, "rolls 0.1 rad apart across pi must be near for the network"
    obs = demo["obs"]
    proprio = np.asarray(features.proprio_features(obs["tcp_pose"], obs["joint_states"], obs["gripper_state"]))
    assert proprio.shape == (len(demo["actions"]), features.PROPRIO_DIM)
    np.testing.assert_allclose(proprio[:, :3], obs["tcp_pose"][:, 4:], atol=1e-6)
    np.testing.assert_allclose(proprio[:, 9:], np.concatenate([obs["joint_states"], obs["gripper_state"]], 1))

    normalizer = Normalizer.fit(np.array([[0.0, 5.0], [2.0, 5.0]]), np.array([[1.0], [3.0]]))
    np.testing.assert_allclose(normalizer.actions(np.array([[0.0, 5.0], [2.0, 5.0]])), [[-1, 0], [1, 0]])
    np.testing.assert_allclose(normalizer.actions_back(normalizer.actions(np.array([[1.5, 5.0]]))), [[1.5, 5.0]])
    assert split_episodes(2, 0.02, 0)[1].size == 1 and split_episodes(1, 0.02, 0)[1].size == 0


def test_temporal_conv_matches_flax_conv_and_ddim_recovers_a_known_sample():
    import flax.linen as nn
    import jax.numpy as jnp

    from partinstruct_mjx.train.diffusion import ddim_sample, squared_cosine_alphas_cumprod
    from partinstruct_mjx.train.model import TemporalConv

    x = jax.random.normal(jax.random.key(1), (2, 16, 6))
    for kernel, stride in ((5, 1), (3, 2), (1, 1)):
        params = TemporalConv(8, kernel, stride).init(jax.random.key(0), x)
        reference = nn.Conv(8, (kernel,), strides=(stride,), padding=kernel // 2).apply(params, x)
        np.testing.assert_allclose(TemporalConv(8, kernel, stride).apply(params, x), reference, atol=1e-5)

    alphas = jnp.asarray(squared_cosine_alphas_cumprod(100))
    assert alphas[0] == pytest.approx(0.99937, abs=1e-5) and alphas[-1] < 1e-6
    clean = jnp.clip(0.5 * jax.random.normal(jax.random.key(2), (3, 16, 10)), -1, 1)

    def exact_noise(sample, levels):
        alpha = alphas[levels][:, None, None]
        return (sample - jnp.sqrt(alpha) * clean) / jnp.sqrt(1 - alpha)

    np.testing.assert_allclose(ddim_sample(exact_noise, alphas, clean.shape, jax.random.key(3), 10), clean, atol=1e-5)


def test_instruction_embeddings_are_cached_by_text(tmp_path, monkeypatch):
    cache = tmp_path / "instructions.npz"
    embeddings = language.InstructionEmbeddings(cache)
    texts = ["Grasp the bottle at its body", "Touch the bottle at its neck", "Grasp the bottle at its body"]
    vectors = embeddings(texts)
    assert vectors.shape == (3, 256) and vectors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1, atol=1e-5)
    np.testing.assert_array_equal(vectors[0], vectors[2])
    assert not np.allclose(vectors[0], vectors[1])
    embeddings.save(cache)
    assert sorted(language.read_cache(cache)) == sorted(set(texts))

    def no_model(texts):
        raise AssertionError(f"embedded {texts} again")

    monkeypatch.setattr(language, "embed_texts", no_model)
    again = language.InstructionEmbeddings(cache)
    np.testing.assert_array_equal(again(texts[:2]), vectors[:2])
    with pytest.raises(AssertionError, match="Lift"):
        again(["Lift the bottle"])
    np.savez(tmp_path / "other.npz", model="t5-small", texts=np.array(["a"]), vectors=np.zeros((1, 512)))
    with pytest.raises(DataError, match="t5-small"):
        language.InstructionEmbeddings(tmp_path / "other.npz")


def test_tiny_model_overfits_the_demos(demo_dir, tmp_path):
    summary = train(tiny_config(demo_dir, tmp_path / "run", steps=120, val_every=120, log_every=20),
                    progress=False)
    losses = [line["loss"] for line in map(json.loads, (tmp_path / "run" / "log.jsonl").read_text().splitlines())
              if "loss" in line]
    assert len(losses) == 6 and summary["best_step"] == 120
    assert losses[-1] < 0.5 * losses[0], f"training loss did not fall: {losses}"


def test_interrupted_run_resumes_to_the_same_weights(demo_dir, tmp_path, monkeypatch):
    straight = tiny_config(demo_dir, tmp_path / "straight")
    train(straight, progress=False)

    resumed = tiny_config(demo_dir, tmp_path / "resumed")
    batch = WindowSampler.batch

    def interrupt_at_step_8(self, step):  # Ctrl-C while batch 8 is drawn: 8 steps are done
        if step == 8:
            raise KeyboardInterrupt
        return batch(self, step)

    monkeypatch.setattr(WindowSampler, "batch", interrupt_at_step_8)
    with pytest.raises(KeyboardInterrupt):
        train(resumed, progress=False)
    monkeypatch.setattr(WindowSampler, "batch", batch)
    manager = checkpoints.checkpoint_manager(tmp_path / "resumed")
    assert manager.all_steps() == [6, 8] and checkpoints.checkpoint_step(manager, "best") == 6
    manager.close()
    assert train(resumed, progress=False)["resumed_from"] == 8

    weights = jax.eval_shape(DP3Policy(TINY, features.ACTION_DIM).init, jax.random.key(0),
                             *example_inputs(straight, (1024, 4)))

    def final(run):
        manager = checkpoints.checkpoint_manager(run)
        step = checkpoints.checkpoint_step(manager, "latest")
        state = checkpoints.restore(manager, step, {"params": weights, "ema_params": weights})
        manager.close()
        return step, state

    (step_a, a), (step_b, b) = final(tmp_path / "straight"), final(tmp_path / "resumed")
    assert step_a == step_b == 12
    jax.tree.map(np.testing.assert_array_equal, a, b)

    def losses(run):
        return [{k: v for k, v in json.loads(line).items() if k != "steps_per_s"}
                for line in (run / "log.jsonl").read_text().splitlines()]

    assert losses(tmp_path / "straight") == losses(tmp_path / "resumed")

    with pytest.raises(DataError, match=r"another config \(lr: 0.003 there, 0.001 now\)"):
        train(tiny_config(demo_dir, tmp_path / "resumed", lr=1e-3), progress=False)


def test_cli_trains_end_to_end_and_resumes(cli_run, capsys):
    run, args = cli_run
    assert main(args) == 0
    assert "trained steps 0-4" in capsys.readouterr().out
    record = json.loads((run / "config.json").read_text())
    assert record["config"]["policy"] == "dp3s" and record["config"]["model"]["down_dims"] == [32]
    assert record["data"]["demos"] == 2 and record["data"]["pcd_sampler"] == "stride"
    assert record["provenance"]["git_sha"] and "wordllama" in record["provenance"]["versions"]
    assert {"config.json", "normalizer.npz", "instructions.npz", "log.jsonl", "checkpoints"} <= {
        p.name for p in run.iterdir()}
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [(line["step"], sorted(line)) for line in log] == [(2, ["step", "val_loss"]),
                                                              (4, ["loss", "lr", "step", "steps_per_s"]),
                                                              (4, ["step", "val_loss"])]
    assert main(args) == 0
    assert "already trained for 4 steps" in capsys.readouterr().out


def test_policy_replans_every_8_steps_in_the_env(cli_run, demo_dir):
    from partinstruct_mjx.env import EnvConfig, PartInstructEnv
    from partinstruct_mjx.train.policy import load_policy

    run, args = cli_run
    if not (run / "config.json").exists():
        assert main(args) == 0
    policy = load_policy(run)
    assert policy.sampler == "stride" and policy.cloud_key == "agentview_part_pcd"
    episodes = read_metadata(demo_dir.parent / "episodes.json")
    path = assets_root() / "objects" / "bottle" / episodes[0].obj_id / "object.xml"
    with PartInstructEnv(path, 2, EnvConfig()) as env:
        observed = []
        point_clouds = env.point_clouds

        def recorded_point_clouds(state, key, sampler="fps"):
            observed.append(int(state.info["steps"][0]))
            return point_clouds(state, key, sampler)

        env.point_clouds = recorded_point_clouds
        key = jax.random.PRNGKey(0)
        state = env.reset(key, episodes)
        policy.reset(env, state, key)
        actions = []
        for step in range(10):
            action = policy.act(env, state, env.instructions(state), jax.random.fold_in(key, step))
            assert action.shape == (2, 7) and action.dtype == np.float32 and np.isfinite(action).all()
            actions.append(action)
            state = env.step(state, action)
        # A fork (another evaluation worker's policy) shares the weights but not the history or the action queue.
        fork, queued = policy.fork(), policy._queue.copy()
        state = env.reset(key, episodes)
        fork.reset(env, state, key)
        np.testing.assert_array_equal(fork.act(env, state, env.instructions(state), jax.random.fold_in(key, 0)),
                                      actions[0])
        assert fork._params is policy._params
        np.testing.assert_array_equal(policy._queue, queued)
    assert observed == [0, 7, 8, 0], "clouds are rendered only for the 2 observation steps of each prediction"
    with PartInstructEnv(path, 2, EnvConfig(rotation="quat")) as env, pytest.raises(DataError, match="Euler"):
        policy.reset(env, env.reset(key, episodes), key)


def test_a_trained_policy_evaluates_the_same_in_worker_processes(cli_run, demo_dir, tmp_path):
    """`partinstruct eval --policy RUN --processes 2` (each process loads the run's policy; the way the full
    evaluation ran on one H100 in docs/results.md) gives the records one process gives."""
    run, args = cli_run
    if not (run / "config.json").exists():
        assert main(args) == 0
    episodes = [replace(e, split="test1") for e in read_metadata(demo_dir.parent / "episodes.json")]
    write_metadata(episodes, tmp_path / "test1.json")
    outcomes = []
    for processes in (1, 2):
        out = tmp_path / f"processes{processes}"
        assert main(["eval", "--policy", str(run), "--metadata", str(tmp_path / "test1.json"), "--splits", "test1",
                     "--batch-size", "2", "--max-steps", "12", "--processes", str(processes), "--out", str(out),
                     "--quiet"]) == 0
        results = json.loads((out / "results.json").read_text())
        assert results["run"]["processes"] == processes and len(results["episodes"]) == 2
        outcomes.append(results["episodes"])
    assert outcomes[0] == outcomes[1]


@pytest.mark.parametrize("args, message", [
    (["--data", "{tmp}/missing", "--policy", "dp3"], "no such data directory"),
    (["--data", "{tmp}", "--policy", "dp3"], "no demonstration files data/*.hdf5"),
    (["--data", "{demos}", "--policy", "dp3", "--down-dims", "12"], "divisible by groups=8"),
])
def test_cli_bad_input_exits_2(demo_dir, tmp_path, capsys, args, message):
    args = [a.format(tmp=tmp_path, demos=demo_dir) for a in args]
    assert main(["train", *args, "--out", str(tmp_path / "run"), "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_cli_refuses_wrong_policy_and_foreign_run_dirs(cli_run, demo_dir, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--data", str(demo_dir), "--policy", "dp4", "--out", str(tmp_path / "run")])
    assert exit_info.value.code == 2 and "invalid choice: 'dp4'" in capsys.readouterr().err
    with pytest.raises(DataError, match="unknown policy 'dp4'"):
        TrainConfig(data=str(demo_dir), policy="dp4", out=str(tmp_path))

    run, args = cli_run
    if not (run / "config.json").exists():
        assert main(args) == 0
    capsys.readouterr()
    assert main([*args, "--seed", "1"]) == 2
    assert "another config (seed: 0 there, 1 now)" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("not a run")
    assert main(["train", "--data", str(demo_dir), "--policy", "dp3", "--out", str(tmp_path / "other")]) == 2
    assert "is not a training run" in capsys.readouterr().err


def test_help_explains_outputs_and_resume(command_help):
    out = command_help("train")
    assert "checkpoints/<step>" in out and "resume" in out and "--policy {dp3,dp3s}" in out
