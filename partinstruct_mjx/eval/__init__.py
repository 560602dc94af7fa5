"""Policy evaluation on the test splits: the policy and planner interfaces, the oracle as both, and the runner.

Names are imported on first use (the runner pulls in JAX and the simulator).
"""

import importlib

_PUBLIC = {
    "EvalConfig": "partinstruct_mjx.eval.config",
    "EvalError": "partinstruct_mjx.errors",
    "Policy": "partinstruct_mjx.eval.policy",
    "OraclePolicy": "partinstruct_mjx.oracle.rollout",
    "load_policy": "partinstruct_mjx.eval.policy",
    "Planner": "partinstruct_mjx.eval.planner",
    "OraclePlanner": "partinstruct_mjx.eval.planner",
    "evaluate": "partinstruct_mjx.eval.runner",
    "aggregate": "partinstruct_mjx.eval.metrics",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'partinstruct_mjx.eval' has no attribute '{name}'")
