"""Orbax checkpoints of a run: RUN/checkpoints/<step>/, keeping the latest and the best by the monitored loss.

A checkpoint holds the whole train state {step, params, ema_params, opt_state}; its metrics hold the validation
loss ('val_loss') or, for a run without held-out demos, the mean training loss since the last one ('train_loss').
A checkpoint written on interruption has no metrics: it is kept as the latest only.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from partinstruct_mjx.errors import DataError


def monitored_loss(metrics: dict) -> float:
    return metrics["val_loss"] if "val_loss" in metrics else metrics["train_loss"]


def checkpoint_manager(run_dir: str | os.PathLike, create: bool = True) -> ocp.CheckpointManager:
    """The manager of RUN/checkpoints (synchronous saves, so a finished `save` is on disk); `create` makes the
    folder."""
    keep = ocp.checkpoint_managers.AnyPreservationPolicy([
        ocp.checkpoint_managers.LatestN(n=1),
        ocp.checkpoint_managers.BestN(get_metric_fn=monitored_loss, reverse=True, n=1,
                                      keep_checkpoints_without_metrics=False)])
    options = ocp.CheckpointManagerOptions(best_fn=monitored_loss, best_mode="min", preservation_policy=keep,
                                           enable_async_checkpointing=False, create=create)
    return ocp.CheckpointManager(Path(run_dir).absolute() / "checkpoints", options=options)


def save(manager: ocp.CheckpointManager, state: dict, metrics: dict | None) -> None:
    """Checkpoint `state` at its step (nothing to do if that step is saved already, e.g. Ctrl-C right after one)."""
    step = int(state["step"])
    if step not in manager.all_steps():
        manager.save(step, args=ocp.args.PyTreeSave(state), metrics=metrics, force=True)


def restore(manager: ocp.CheckpointManager, step: int, template: dict) -> dict:
    """The subtree `template` (a dict of some of the state's fields, arrays or shape structs) of checkpoint `step`."""
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, template)
    try:
        return manager.restore(step, args=ocp.args.PyTreeRestore(
            item=abstract, restore_args=ocp.checkpoint_utils.construct_restore_args(abstract), partial_restore=True))
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise DataError(f"{manager.directory}/{step}: cannot restore the checkpoint ({err})") from None


def checkpoint_step(manager: ocp.CheckpointManager, which: str | int) -> int:
    """The step of checkpoint 'best' (the latest while none has a loss), 'latest' or a step number; DataError if
    there is none such."""
    steps = manager.all_steps()
    if which == "best":
        step = manager.best_step()
        step = manager.latest_step() if step is None else step
    elif which == "latest":
        step = manager.latest_step()
    else:
        step = int(which) if str(which).isdigit() else None
    if step is None or step not in steps:
        raise DataError(f"{manager.directory}: no checkpoint '{which}' (steps saved: {sorted(steps) or 'none'})")
    return step
