"""The low-level policy interface the evaluation runner drives, the oracle as such a policy, and policy loading."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from partinstruct_mjx.eval.config import ORACLE, EvalError
from partinstruct_mjx.oracle.backtrack import SEGMENT_TRIES
from partinstruct_mjx.oracle.rollout import OraclePolicy


@runtime_checkable
class Policy(Protocol):
    """Acts in every scene of a `PartInstructEnv` batch; may read the env and its state (observations: `state.obs`,
    `env.point_clouds(state, key)`, `env.camera_observations(state)`).

    Optional: `fork() -> Policy`, a policy for another worker thread that shares what is read-only (weights) and keeps
    its own per-batch state; `evaluate` runs objects in several threads only when the policy (and planner) can fork.
    """

    def reset(self, env, state, key) -> None:
        """New episodes in every scene of the batch (`env.episodes`)."""

    def act(self, env, state, instructions: list[str], key) -> np.ndarray:
        """(B, 7) Euler action for this step: xyz, Euler 'xyz', finger opening in metres (spec 1.6)."""


def load_policy(spec: str, oracle_tries: int | None = None) -> Policy:
    """'oracle' (looking ahead with `oracle_tries` tries per grasp or touch; None: the default), or the policy of a
    training run directory (`partinstruct_mjx.train.policy.load_policy`)."""
    if spec == ORACLE:
        return OraclePolicy(SEGMENT_TRIES if oracle_tries is None else oracle_tries)
    run_dir = Path(spec)
    if not run_dir.exists():
        raise EvalError(f"policy run directory not found: {run_dir} (expected a training run directory or "
                        f"'{ORACLE}')")
    if not run_dir.is_dir():
        raise EvalError(f"policy {run_dir} is not a directory (expected a training run directory or '{ORACLE}')")
    try:
        from partinstruct_mjx.train.policy import load_policy as load_trained
    except ModuleNotFoundError as err:
        if err.name not in ("partinstruct_mjx.train", "partinstruct_mjx.train.policy"):
            raise
        raise EvalError(f"cannot load the policy in {run_dir}: this installation has no "
                        f"partinstruct_mjx.train.policy") from None
    policy = load_trained(run_dir)
    if not isinstance(policy, Policy):
        raise EvalError(f"{run_dir}: load_policy returned a {type(policy).__name__}, which lacks reset/act")
    return policy
