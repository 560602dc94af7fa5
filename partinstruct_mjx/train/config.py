"""Training configuration: the policy variants, the model's sizes and the optimisation settings (frozen dataclasses).

Defaults follow DP3 (Ze et al. 2024) and Diffusion Policy as the original's DP3-S baseline uses them (spec 11):
horizon 16, 2 observation steps, 8 executed actions, 100 DDPM steps, 10 DDIM steps, AdamW 1e-4 with cosine decay.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from partinstruct_mjx.errors import DataError

POLICIES = {"dp3": "agentview_pcd", "dp3s": "agentview_part_pcd"}
"""Policy variant -> the point-cloud observation it sees: xyz only, or xyz plus the target-part flag."""
CLOUD_CHANNELS = {"agentview_pcd": 3, "agentview_part_pcd": 4}
INSTRUCTION_SOURCES = ("skill", "task")
"""Which instruction a step is labelled with: its skill's (the evaluation default) or the episode's task."""


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of the DP3-style policy and its diffusion process.

    Attributes:
      horizon: actions predicted per denoising (the U-Net's sequence length; divisible by 2**(len(down_dims)-1)).
      obs_steps: observation steps the policy is conditioned on (the current one and those before it).
      action_steps: predicted actions executed before the policy predicts again.
      encoder_dims: widths of the per-point MLP of the point-cloud encoder (LayerNorm + ReLU after each).
      feature_dim: width of the cloud, proprioception and instruction features.
      step_embed_dim: width of the diffusion-step embedding.
      down_dims: channels of the U-Net levels.
      kernel_size: temporal convolution width.
      groups: GroupNorm groups (must divide every width of down_dims).
      train_timesteps: DDPM noise levels (squared-cosine schedule, epsilon prediction).
      inference_steps: DDIM steps when acting.
    """

    horizon: int = 16
    obs_steps: int = 2
    action_steps: int = 8
    encoder_dims: tuple[int, ...] = (64, 128, 256)
    feature_dim: int = 64
    step_embed_dim: int = 128
    down_dims: tuple[int, ...] = (512, 1024, 2048)
    kernel_size: int = 5
    groups: int = 8
    train_timesteps: int = 100
    inference_steps: int = 10

    def __post_init__(self):
        if self.obs_steps < 1 or self.action_steps < 1 or self.obs_steps - 1 + self.action_steps > self.horizon:
            raise DataError(f"obs_steps {self.obs_steps} and action_steps {self.action_steps} must be >= 1 and "
                            f"fit in the horizon {self.horizon} (obs_steps - 1 + action_steps <= horizon)")
        if self.horizon % 2 ** (len(self.down_dims) - 1):
            raise DataError(f"horizon {self.horizon} must be divisible by 2**{len(self.down_dims) - 1} for "
                            f"{len(self.down_dims)} U-Net levels")
        if any(width % self.groups for width in self.down_dims):
            raise DataError(f"every U-Net width {self.down_dims} must be divisible by groups={self.groups}")
        if not 1 <= self.inference_steps <= self.train_timesteps:
            raise DataError(f"inference_steps must be in [1, {self.train_timesteps}], got {self.inference_steps}")


@dataclass(frozen=True)
class TrainConfig:
    """One training run.

    Attributes:
      data: run directory of `partinstruct demos` (its data/<category>.hdf5 files are read).
      policy: 'dp3' (agentview_pcd) or 'dp3s' (agentview_part_pcd, with the target-part flag).
      out: run directory for checkpoints, config.json, normalizer.npz, instructions.npz and log.jsonl.
      steps: optimiser steps in all.
      batch_size: windows per step.
      lr: peak learning rate of AdamW.
      warmup_steps: linear warm-up steps before the cosine decay (at most a tenth of `steps`, see `resolved`).
      weight_decay: AdamW weight decay.
      ema: keep an exponential moving average of the weights (used for validation and acting).
      val_ratio: fraction of the demos held out for the validation loss (at least 1 when there are 2 or more).
      val_every: steps between validations; each one also writes a checkpoint.
      max_val_batches: validation batches at most (a fixed seeded subset of the held-out windows beyond that).
      log_every: steps between loss-log lines and progress-bar updates.
      instructions: 'skill' (the instruction of each step's skill) or 'task' (the episode's task instruction).
      seed: seed of the initial weights, the validation split, the batches and the diffusion noise.
    """

    data: str
    policy: str
    out: str
    steps: int = 100_000
    batch_size: int = 128
    lr: float = 1e-4
    warmup_steps: int = 500
    weight_decay: float = 1e-6
    ema: bool = True
    val_ratio: float = 0.02
    val_every: int = 1000
    max_val_batches: int = 16
    log_every: int = 50
    instructions: str = "skill"
    seed: int = 0
    model: ModelConfig = field(default_factory=ModelConfig)

    def __post_init__(self):
        if self.policy not in POLICIES:
            raise DataError(f"unknown policy '{self.policy}'; expected one of {', '.join(POLICIES)}")
        if self.instructions not in INSTRUCTION_SOURCES:
            raise DataError(f"unknown instructions '{self.instructions}'; expected one of "
                            f"{', '.join(INSTRUCTION_SOURCES)}")
        for name in ("steps", "batch_size", "val_every", "max_val_batches", "log_every"):
            if getattr(self, name) < 1:
                raise DataError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.val_ratio < 1:
            raise DataError(f"val_ratio must be in [0, 1), got {self.val_ratio}")
        if self.lr <= 0 or self.warmup_steps < 0 or self.weight_decay < 0:
            raise DataError(f"lr must be > 0 and warmup_steps, weight_decay >= 0; got {self.lr}, "
                            f"{self.warmup_steps}, {self.weight_decay}")

    @property
    def cloud_key(self) -> str:
        return POLICIES[self.policy]

    def resolved(self) -> TrainConfig:
        """The settings actually used: absolute paths, warm-up capped at a tenth of the steps (so that short runs
        decay too)."""
        return dataclasses.replace(self, data=str(Path(self.data).resolve()), out=str(Path(self.out).resolve()),
                                   warmup_steps=min(self.warmup_steps, self.steps // 10))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> TrainConfig:
        """Inverse of to_dict (JSON lists back to tuples)."""
        model = {key: tuple(value) if isinstance(value, list) else value for key, value in values["model"].items()}
        return cls(**{**values, "model": ModelConfig(**model)})
