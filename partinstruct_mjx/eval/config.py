"""Evaluation settings (one frozen dataclass, recorded in results.json) and the evaluation error."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from partinstruct_mjx.errors import EvalError
from partinstruct_mjx.tasks.episodes import SPLITS

TEST_SPLITS = ("test1", "test2", "test3", "test4", "test5")
SPLIT_TITLES = {"train": "Train", "test1": "Test 1 (OS)", "test2": "Test 2 (OI)", "test3": "Test 3 (TP)",
                "test4": "Test 4 (TC)", "test5": "Test 5 (OC)"}
"""Column titles of the paper's success table (spec 9.4)."""
MODES = ("skill", "task")
PLANNERS = ("oracle",)
ORACLE = "oracle"
DEFAULT_EPISODES_PER_SPLIT = 360
"""5 x 360 = 1,800 episodes, the size of the paper's evaluation set (spec 9.4)."""


@dataclass(frozen=True)
class EvalConfig:
    """What to evaluate and how.

    Attributes:
      policy: 'oracle' or a training run directory (loaded by `partinstruct_mjx.train.policy.load_policy`); a label
        when `evaluate` is handed a policy object.
      splits: splits to evaluate, in table order.
      mode: 'skill' (success = the ground-truth skill chain completed, the original's evaluation) or 'task'
        (success = the task's goals, spec 7).
      episodes_per_split: episodes per split, spread over its task types and categories (all of `metadata`'s when
        None and a metadata file is given).
      batch_size: scenes of one object simulated together.
      backend: 'mujoco' (C MuJoCo on CPU threads) or 'mjx'.
      planner: None (instructions from the env) or 'oracle'; a label when `evaluate` is handed a planner object.
      planner_every: steps between planner consultations.
      videos: MP4s of the first K episodes of each split.
      seed: seed of the generated episodes and of the policy's random keys.
      max_steps: cap on every episode's horizon (None: the split's, 250 or 400 steps); for smoke tests.
      metadata: episode metadata JSON to draw the episodes from instead of generating them.
      categories: only these object categories.
      assets: assets root with catalog.json (None: the built-in library).
      num_threads: physics threads of the mujoco backend (None: all cores).
      workers: objects rolled out at once, each in a thread with its own env (num_threads // workers physics
        threads) and its own fork of the policy and planner (None: 2 on the mujoco backend, 1 on mjx, 1 for a
        policy or planner without `fork`).
      processes: worker processes (1: none); each rolls out one object at a time with its own env, its share of
        `num_threads` and its own copy of the policy and planner, loaded from this config. Unlike worker threads,
        processes do not share one Python interpreter lock or one JAX runtime, which bound the threads' speed on a
        many-core machine.
      oracle_tries: `--policy oracle` only: tries per grasp or touch in its private look-ahead copy of the env
        (1: the closed-loop oracle alone; None: `oracle.backtrack.SEGMENT_TRIES`).
    `videos`, `num_threads`, `workers` and `processes` do not change outcomes, so a run directory may be resumed
    with other values.
    """

    policy: str = ORACLE
    splits: tuple[str, ...] = TEST_SPLITS
    mode: str = "skill"
    episodes_per_split: int | None = DEFAULT_EPISODES_PER_SPLIT
    batch_size: int = 16
    backend: str = "mujoco"
    planner: str | None = None
    planner_every: int = 1
    videos: int = 0
    seed: int = 0
    max_steps: int | None = None
    metadata: str | None = None
    categories: tuple[str, ...] | None = None
    assets: str | None = None
    num_threads: int | None = None
    oracle_tries: int | None = None
    workers: int | None = None
    processes: int = 1

    def __post_init__(self):
        unknown = [s for s in self.splits if s not in SPLITS]
        if unknown:
            raise EvalError(f"unknown split '{unknown[0]}'; expected some of {', '.join(SPLITS)}")
        if not self.splits or len(set(self.splits)) != len(self.splits):
            raise EvalError(f"splits must be distinct and at least one, got {list(self.splits)}")
        if self.mode not in MODES:
            raise EvalError(f"unknown mode '{self.mode}'; expected one of {', '.join(MODES)}")
        if self.backend not in ("mujoco", "mjx"):
            raise EvalError(f"unknown backend '{self.backend}'; expected mujoco or mjx")
        for name in ("batch_size", "planner_every", "episodes_per_split", "max_steps", "oracle_tries",
                     "workers", "processes"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise EvalError(f"{name} must be >= 1, got {value}")
        if self.processes > 1 and (self.workers or 1) > 1:
            raise EvalError(f"workers ({self.workers}) and processes ({self.processes}): choose one (a process "
                            f"rolls out one object at a time)")
        if self.episodes_per_split is None and self.metadata is None:
            raise EvalError("episodes_per_split is needed unless episodes come from a metadata file")
        if self.videos < 0:
            raise EvalError(f"videos must be >= 0, got {self.videos}")

    def identity(self) -> dict:
        """The settings a resumed run must share with its run directory: all that can change an outcome."""
        fields = asdict(self)
        del fields["num_threads"], fields["videos"], fields["workers"], fields["processes"]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in fields.items()}
