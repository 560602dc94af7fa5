"""The training loop: DDPM noise-prediction loss, AdamW with warm-up and cosine decay, EMA, validation, checkpoints.

A run directory holds config.json (resolved config, data summary, provenance), normalizer.npz, instructions.npz,
log.jsonl (training and validation losses) and checkpoints/. Running the same config on an existing run directory
resumes from its latest checkpoint; batch k and the noise of step k depend only on the seed and k, so an
interrupted and resumed run computes the same weights as an uninterrupted one.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from partinstruct_mjx.atomic import atomic_write
from partinstruct_mjx.errors import DataError
from partinstruct_mjx.train import checkpoints, features
from partinstruct_mjx.train.config import TrainConfig
from partinstruct_mjx.train.dataset import DemoData, Normalizer, WindowSampler, load_demos, split_episodes
from partinstruct_mjx.train.diffusion import add_noise, squared_cosine_alphas_cumprod
from partinstruct_mjx.train.language import EMBEDDING_DIM, InstructionEmbeddings
from partinstruct_mjx.train.language import MODEL as EMBEDDING_MODEL
from partinstruct_mjx.train.model import DP3Policy, init_params

CONFIG_FILE = "config.json"
NORMALIZER_FILE = "normalizer.npz"
INSTRUCTIONS_FILE = "instructions.npz"
LOG_FILE = "log.jsonl"
EMA_POWER = 0.75
EMA_MAX_DECAY = 0.9999
ADAM_BETAS = (0.95, 0.999)


def ema_decay(step: jnp.ndarray, enabled: bool) -> jnp.ndarray:
    """Decay of the weight average after `step` optimiser steps (diffusion_policy's EMAModel: power 0.75, at most
    0.9999, plain copies for the first two steps); 0 when EMA is off."""
    if not enabled:
        return jnp.zeros(())
    after = jnp.maximum(step - 1, 0).astype(jnp.float32)
    return jnp.where(after > 0, jnp.minimum(1 - (1 + after) ** -EMA_POWER, EMA_MAX_DECAY), 0.0)


def diffusion_loss(model: DP3Policy, alphas_cumprod: jnp.ndarray, params, batch: dict, key: jax.Array,
                   weight: jnp.ndarray | None = None) -> jnp.ndarray:
    """Mean squared error of the predicted noise at uniformly drawn noise levels (weighted per sample)."""
    actions = batch["actions"]
    noise_key, level_key = jax.random.split(key)
    noise = jax.random.normal(noise_key, actions.shape)
    levels = jax.random.randint(level_key, actions.shape[:1], 0, alphas_cumprod.shape[0])
    predicted = model.apply(params, add_noise(alphas_cumprod, actions, noise, levels), levels, batch["clouds"],
                            batch["proprio"], batch["instruction"])
    per_sample = jnp.mean((predicted - noise) ** 2, axis=(1, 2))
    return jnp.mean(per_sample) if weight is None else jnp.sum(per_sample * weight) / jnp.sum(weight)


def learning_rate(config: TrainConfig, step: int) -> float:
    """Linear warm-up from 0 to config.lr, then cosine decay to 0 at config.steps (diffusers' 'cosine')."""
    if step < config.warmup_steps:
        return config.lr * step / config.warmup_steps
    progress = (step - config.warmup_steps) / max(1, config.steps - config.warmup_steps)
    return config.lr * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """AdamW whose learning rate is an input of each step (hyperparameters live in the optimiser state, so one
    compiled step serves every schedule, step count and seed)."""
    return optax.inject_hyperparams(optax.adamw)(learning_rate=config.lr, b1=ADAM_BETAS[0], b2=ADAM_BETAS[1],
                                                 eps=1e-8, weight_decay=config.weight_decay)


def example_inputs(config: TrainConfig, cloud_shape: tuple[int, ...]) -> tuple:
    """Arguments of DP3Policy.__call__ for one sample (shapes only matter)."""
    m = config.model
    return (jnp.zeros((1, m.horizon, features.ACTION_DIM)), jnp.zeros((1,), jnp.int32),
            jnp.zeros((1, m.obs_steps, *cloud_shape)), jnp.zeros((1, m.obs_steps, features.PROPRIO_DIM)),
            jnp.zeros((1, EMBEDDING_DIM)))


def train(config: TrainConfig, progress: bool = True) -> dict:
    """Train (or resume) the run `config.out`; returns what was done: steps, losses, the best checkpoint."""
    config = config.resolved()
    run = Path(config.out)
    previous = _previous_run(run, config)
    done = _latest_step(run) if previous is not None else 0
    summary = {"run": str(run), "resumed_from": done, "steps": config.steps, "val_loss": None, "train_loss": None}
    if done >= config.steps:
        return summary
    data, sampler, validation = _training_data(config, run, previous, progress)
    summary |= {"train_windows": len(sampler), "val_batches": len(validation)}

    model = DP3Policy(config.model, features.ACTION_DIM)
    alphas = jnp.asarray(squared_cosine_alphas_cumprod(config.model.train_timesteps))
    tx = optimizer(config)

    def initial_state(params):
        return {"step": jnp.zeros((), jnp.int32), "params": params, "ema_params": params,
                "opt_state": tx.init(params)}

    inputs = example_inputs(config, data.clouds.shape[1:])
    if previous is None:
        _write_config(run, config, data)
    manager = checkpoints.checkpoint_manager(run)
    if done:
        state = checkpoints.restore(manager, done, jax.eval_shape(
            lambda: initial_state(model.init(jax.random.key(0), *inputs))))
    else:
        state = initial_state(init_params(model, inputs, config.seed))
    _truncate_log(run / LOG_FILE, done)
    # RngBitGenerator keys: threefry's random bits take seconds to compile on a CPU, these a fraction of one
    train_key, val_key = jax.random.split(jax.random.key(config.seed, impl="rbg"))

    @jax.jit
    def train_step(state, batch, key, lr):
        key = jax.random.fold_in(key, state["step"])
        loss, grads = jax.value_and_grad(lambda p: diffusion_loss(model, alphas, p, batch, key))(state["params"])
        opt_state = state["opt_state"]
        lr = jnp.asarray(lr, jnp.float32)  # not weakly typed, so the returned state compiles no second step
        opt_state = opt_state._replace(hyperparams={**opt_state.hyperparams, "learning_rate": lr})
        updates, opt_state = tx.update(grads, opt_state, state["params"])
        params = optax.apply_updates(state["params"], updates)
        decay = ema_decay(state["step"], config.ema)
        ema = jax.tree.map(lambda e, p: decay * e + (1 - decay) * p, state["ema_params"], params)
        return {"step": state["step"] + 1, "params": params, "ema_params": ema, "opt_state": opt_state}, loss

    @jax.jit
    def validation_loss(params, batch, weight, key):
        return diffusion_loss(model, alphas, params, batch, key, weight)

    def validate() -> float:
        losses = [float(validation_loss(state["ema_params"], batch, weight, jax.random.fold_in(val_key, i)))
                  for i, (batch, weight) in enumerate(validation)]
        return float(np.average(losses, weights=[weight.sum() for _, weight in validation]))

    from tqdm import tqdm

    pending: list[jax.Array] = []
    since_checkpoint: list[float] = []
    postfix: dict[str, str] = {}
    tick = time.perf_counter()
    bar = tqdm(total=config.steps, initial=done, desc=f"train {config.policy}", unit="step", disable=not progress)
    try:
        with open(run / LOG_FILE, "a") as log:
            for step in range(done, config.steps):
                state, loss = train_step(state, sampler.batch(step), train_key, learning_rate(config, step))
                pending.append(loss)
                done = step + 1
                if done % config.log_every == 0 or done == config.steps:
                    mean = float(np.mean([float(x) for x in pending]))
                    rate = len(pending) / (time.perf_counter() - tick)
                    _log(log, {"step": done, "loss": mean, "lr": learning_rate(config, step), "steps_per_s": rate})
                    postfix["loss"] = f"{mean:.4f}"
                    bar.set_postfix(postfix, refresh=False)
                    bar.update(len(pending))
                    summary["train_loss"] = mean
                    since_checkpoint.append(mean)
                    pending, tick = [], time.perf_counter()
                if done % config.val_every == 0 or done == config.steps:
                    if validation:
                        summary["val_loss"] = validate()
                        metrics = {"val_loss": summary["val_loss"]}
                        _log(log, {"step": done, "val_loss": summary["val_loss"]})
                        postfix["val"] = f"{summary['val_loss']:.4f}"
                        bar.set_postfix(postfix, refresh=False)
                    else:
                        metrics = {"train_loss": float(np.mean(since_checkpoint))}
                    since_checkpoint = []
                    checkpoints.save(manager, state, metrics)
        summary["best_step"] = checkpoints.checkpoint_step(manager, "best")
    except KeyboardInterrupt:
        if int(state["step"]) > 0:
            checkpoints.save(manager, state, None)
        raise
    finally:
        bar.close()
        manager.close()
    return summary


def _training_data(config: TrainConfig, run: Path, previous: dict | None,
                   progress: bool) -> tuple[DemoData, WindowSampler, list]:
    """The demos, the training sampler and the validation batches; writes (or, resuming, reads) the normalizer
    and the instruction embeddings of the run."""
    data = load_demos(config.data, config.cloud_key, config.instructions, progress=progress)
    if previous is not None and previous["data"] != json.loads(json.dumps(data.summary())):
        raise DataError(f"{run} was trained on other data ({previous['data']['demos']} demos, "
                        f"{previous['data']['steps']} steps; now {data.summary()['demos']} and "
                        f"{data.summary()['steps']}); use a new --out for the changed data")
    run.mkdir(parents=True, exist_ok=True)
    embeddings = InstructionEmbeddings(run / INSTRUCTIONS_FILE)
    vectors = embeddings(data.instructions)
    embeddings.save(run / INSTRUCTIONS_FILE)
    train_demos, val_demos = split_episodes(len(data.episode_ends), config.val_ratio, config.seed)
    if previous is None:
        steps = np.concatenate([np.arange(data.episode_starts[e], data.episode_ends[e]) for e in train_demos])
        normalizer = Normalizer.fit(data.actions[steps], data.proprio[steps])
        normalizer.save(run / NORMALIZER_FILE)
    else:
        normalizer = Normalizer.load(run / NORMALIZER_FILE)
    sampler = WindowSampler(data, train_demos, normalizer, vectors, config.model, config.batch_size, config.seed)
    validation = (WindowSampler(data, val_demos, normalizer, vectors, config.model, config.batch_size, config.seed)
                  .validation_batches(config.max_val_batches) if len(val_demos) else [])
    return data, sampler, validation


def _latest_step(run: Path) -> int:
    """Optimiser steps of the run's latest checkpoint (0 without one)."""
    if not (run / "checkpoints").exists():
        return 0
    manager = checkpoints.checkpoint_manager(run, create=False)
    try:
        return manager.latest_step() or 0
    finally:
        manager.close()


def _previous_run(run: Path, config: TrainConfig) -> dict | None:
    """The config.json of an existing run with the same config (None for a new run); DataError for another config
    or a non-empty directory that is no run."""
    path = run / CONFIG_FILE
    if not path.exists():
        if run.exists() and any(run.iterdir()):
            raise DataError(f"{run} exists and is not a training run (no {CONFIG_FILE}); choose a new --out")
        return None
    try:
        previous = json.loads(path.read_text())
        stored = previous["config"]
    except (ValueError, KeyError):
        raise DataError(f"{path}: unreadable run config; choose a new --out") from None
    mine = json.loads(json.dumps(config.to_dict()))
    stored = {**stored, "out": mine["out"]}  # the same run may be reached by another path
    if stored != mine:
        changed = _differences(stored, mine)
        raise DataError(f"{run} holds a run with another config ({'; '.join(changed)}); resume it with the same "
                        "settings or choose a new --out")
    return previous


def _differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: {a} there, {b} now")
    return out


def _write_config(run: Path, config: TrainConfig, data: DemoData) -> None:
    from partinstruct_mjx.provenance import provenance

    record = {"config": config.to_dict(), "data": data.summary(), "instruction_model": EMBEDDING_MODEL,
              "provenance": provenance()}
    record["provenance"]["versions"].update(_extra_versions())
    with atomic_write(run / CONFIG_FILE) as file:
        json.dump(record, file, indent=1)
        file.write("\n")


def _extra_versions() -> dict[str, str]:
    import importlib.metadata

    versions = {}
    for name in ("orbax-checkpoint", "wordllama"):
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return versions


def _log(file, record: dict) -> None:
    file.write(json.dumps(record) + "\n")
    file.flush()


def _truncate_log(path: Path, step: int) -> None:
    """Drop log lines after `step` (written after the checkpoint a resumed run starts from)."""
    if not path.exists():
        return
    lines = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
    with atomic_write(path) as file:
        file.writelines(line + "\n" for line in lines)
