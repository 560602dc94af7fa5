"""A trained run as a policy for evaluation: observation history, DDIM planning, open-loop action chunks.

`load_policy(run_dir)` returns a `DiffusionPolicy` with the evaluator's interface:

    reset(env, state, key) -> None                          new episodes in every scene of the batch
    act(env, state, instructions, key) -> np.ndarray (B, 7)  absolute Euler action for this step

It keeps the last `obs_steps` observations (the first one repeated after a reset, as diffusion_policy's
MultiStepWrapper does), predicts `horizon` actions for all scenes together whenever the previous `action_steps`
are used up, and executes them open loop. Point clouds are rendered only for the steps a prediction will see, with
the sampler the training demos were rendered with.
"""

from __future__ import annotations

import copy
import json
import os
from collections import deque
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.errors import DataError
from partinstruct_mjx.train import checkpoints, features
from partinstruct_mjx.train.config import ModelConfig, TrainConfig
from partinstruct_mjx.train.dataset import Normalizer
from partinstruct_mjx.train.diffusion import ddim_sample, squared_cosine_alphas_cumprod
from partinstruct_mjx.train.language import MODEL as INSTRUCTION_MODEL
from partinstruct_mjx.train.language import InstructionEmbeddings
from partinstruct_mjx.train.model import DP3Policy
from partinstruct_mjx.train.trainer import CONFIG_FILE, INSTRUCTIONS_FILE, NORMALIZER_FILE, example_inputs


class DiffusionPolicy:
    """A DP3 / DP3-S policy acting in a batched `PartInstructEnv` (any batch size, one compile per size)."""

    def __init__(self, model_config: ModelConfig, params, normalizer: Normalizer, cloud_key: str, sampler: str,
                 embeddings: InstructionEmbeddings, name: str = "policy"):
        self.config = model_config
        self.cloud_key = cloud_key
        self.sampler = sampler
        self.embeddings = embeddings
        self.name = name
        self._normalizer = normalizer
        self._params = params
        self._history: deque = deque(maxlen=model_config.obs_steps)
        self._queue = np.zeros((0, 0, 7), np.float32)
        model = DP3Policy(model_config, features.ACTION_DIM)
        alphas = jnp.asarray(squared_cosine_alphas_cumprod(model_config.train_timesteps))
        first = model_config.obs_steps - 1

        @jax.jit
        def plan(params, clouds, proprio, instruction, key):
            condition = model.apply(params, clouds, proprio, instruction, method=DP3Policy.encode)

            def predict_noise(sample, timesteps):
                return model.apply(params, sample, timesteps, condition, method=DP3Policy.denoise)

            shape = (clouds.shape[0], model_config.horizon, features.ACTION_DIM)
            sample = ddim_sample(predict_noise, alphas, shape, key, model_config.inference_steps)
            actions = features.actions_from_model(normalizer.actions_back(sample))
            return actions[:, first:first + model_config.action_steps]

        self._plan = plan

    def fork(self) -> DiffusionPolicy:
        """A policy for another worker thread: the same weights and compiled sampler, its own history and queue."""
        other = copy.copy(self)
        other._history = deque(maxlen=self.config.obs_steps)
        other._queue = np.zeros((0, 0, 7), np.float32)
        return other

    def reset(self, env, state, key) -> None:
        """Forget the history and the queued actions (`state` and `key` are not needed: the first `act` observes)."""
        if env.config.action_size != 7:
            raise DataError(f"{self.name} predicts 7-D Euler actions; make the env with rotation='euler', not "
                            f"'{env.config.rotation}'")
        self._history.clear()
        self._queue = np.zeros((0, 0, 7), np.float32)

    def act(self, env, state, instructions: list[str], key) -> np.ndarray:
        """(B, 7) float32 [x, y, z, roll, pitch, yaw, finger] for the current step of every scene."""
        cloud_key, plan_key = jax.random.split(key)
        if self._queue.shape[1] < self.config.obs_steps:
            self._observe(env, state, cloud_key)
        if self._queue.shape[1] == 0:
            if len(instructions) != env.batch_size:
                raise DataError(f"{len(instructions)} instructions for {env.batch_size} scenes")
            clouds, proprio = (jnp.stack(x, axis=1) for x in zip(*self._history))
            instruction = jnp.asarray(self.embeddings(list(instructions)))
            self._queue = np.asarray(self._plan(self._params, clouds, proprio, instruction, plan_key))
        action, self._queue = self._queue[:, 0], self._queue[:, 1:]
        return action

    def _observe(self, env, state, key) -> None:
        cloud = env.point_clouds(state, key, sampler=self.sampler)[self.cloud_key]
        proprio = self._normalizer.proprio(features.proprio_features(*(state.obs[k] for k in features.PROPRIO_KEYS)))
        self._history.append((cloud, proprio))
        while len(self._history) < self._history.maxlen:
            self._history.appendleft((cloud, proprio))


def load_policy(run_dir: str | os.PathLike, checkpoint: str | int = "best") -> DiffusionPolicy:
    """The policy of a training run: its EMA weights at checkpoint 'best' (lowest monitored loss), 'latest' or a
    step. DataError if the directory is no training run or lacks the checkpoint."""
    run = Path(run_dir)
    try:
        record = json.loads((run / CONFIG_FILE).read_text())
        config = TrainConfig.from_dict(record["config"])
        cloud_shape = tuple(record["data"]["cloud_shape"])
        sampler = record["data"]["pcd_sampler"]
        instruction_model = record["instruction_model"]
    except FileNotFoundError:
        raise DataError(f"{run}: no {CONFIG_FILE}; not a training run directory (`partinstruct train --out`)") from None
    except (ValueError, KeyError, TypeError) as err:
        raise DataError(f"{run / CONFIG_FILE}: malformed run config ({err})") from None
    if instruction_model != INSTRUCTION_MODEL:
        raise DataError(f"{run} was trained with instruction embeddings of '{instruction_model}'; this version "
                        f"embeds with '{INSTRUCTION_MODEL}'")
    model = DP3Policy(config.model, features.ACTION_DIM)
    template = {"ema_params": jax.eval_shape(model.init, jax.random.key(0), *example_inputs(config, cloud_shape))}
    manager = checkpoints.checkpoint_manager(run, create=False)
    try:
        step = checkpoints.checkpoint_step(manager, checkpoint)
        params = checkpoints.restore(manager, step, template)["ema_params"]
    finally:
        manager.close()
    return DiffusionPolicy(config.model, params, Normalizer.load(run / NORMALIZER_FILE), config.cloud_key, sampler,
                           InstructionEmbeddings(run / INSTRUCTIONS_FILE), name=f"{config.policy} {run.name}@{step}")
