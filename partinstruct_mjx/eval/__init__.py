"""Policy evaluation on the test splits: the policy and planner interfaces, the oracle as both, and the runner.

Names are imported on first use (the runner pulls in JAX and the simulator).
"""

from partinstruct_mjx.lazy import lazy_getattr

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
    "compare": "partinstruct_mjx.eval.compare",
}
__all__ = sorted(_PUBLIC)

__getattr__ = lazy_getattr(__name__, _PUBLIC)
