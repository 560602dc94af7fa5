"""Paired comparison of two evaluation runs on the same episodes (`partinstruct compare A B`).

Two policies (or two versions of one) evaluated on the same episodes differ only where their outcomes differ: the
episodes B succeeds on and A fails (gained) and the other way round (lost). Under "no difference" each of those
discordant episodes is a fair coin, so the two-sided exact McNemar test (a binomial test on gained against lost)
says how surprising the split is. It is far more sensitive than comparing the two success rates with their standard
errors, which ignores that both runs saw the same episodes.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from partinstruct_mjx.eval.config import SPLIT_TITLES, EvalError
from partinstruct_mjx.eval.metrics import markdown_table

_SAME_EPISODE = ("category", "obj_id", "task_type", "task_instruction")
"""Record fields two runs must agree on for an ep_id of a split to be the same episode."""


def load_results(path: str | Path) -> dict:
    """results.json of an evaluation run directory (or the file itself)."""
    path = Path(path)
    file = path / "results.json" if path.is_dir() else path
    if not file.is_file():
        raise EvalError(f"no evaluation results at {file} (expected a `partinstruct eval --out` directory)")
    try:
        results = json.loads(file.read_text())
    except json.JSONDecodeError as error:
        raise EvalError(f"{file} is not a `partinstruct eval` results.json ({error})") from None
    if not isinstance(results, dict) or not {"episodes", "config", "label", "complete"} <= set(results):
        raise EvalError(f"{file} is not a `partinstruct eval` results.json (no episodes, config, label or complete)")
    return results


def mcnemar_p(gained: int, lost: int) -> float:
    """Two-sided exact McNemar p-value: the chance of a split at least this uneven of gained + lost fair coins."""
    n = gained + lost
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(gained, lost) + 1)) / 2 ** n
    return min(1.0, 2 * tail)


def compare(a: dict, b: dict) -> dict:
    """The paired comparison of results `a` and `b` on the episodes both ran: counts overall, per split and per
    task type, and the discordant episodes. Raises EvalError where the runs' success criteria or episodes differ."""
    if a["config"]["mode"] != b["config"]["mode"]:
        raise EvalError(f"the runs judge success differently (--mode {a['config']['mode']} and "
                        f"{b['config']['mode']}); compare runs of one mode")
    first = {(r["split"], r["ep_id"]): r for r in a["episodes"]}
    second = {(r["split"], r["ep_id"]): r for r in b["episodes"]}
    shared = sorted(first.keys() & second.keys())
    for key in shared:
        differ = [f for f in _SAME_EPISODE if first[key].get(f) != second[key].get(f)]
        if differ:
            raise EvalError(f"episode {key[1]} of {key[0]} is not the same in both runs ({differ[0]}: "
                            f"{first[key].get(differ[0])!r} and {second[key].get(differ[0])!r}); were they drawn "
                            "with the same --seed or --metadata?")
    pairs = [(first[k], second[k]) for k in shared]
    changed = [{"split": x["split"], "ep_id": x["ep_id"], "category": x["category"], "obj_id": x["obj_id"],
                "task_type": x["task_type"], "a_success": x["success"], "b_success": y["success"],
                "a_stopped_skill": x["stopped_skill"], "b_stopped_skill": y["stopped_skill"]}
               for x, y in pairs if x["success"] != y["success"]]
    return {"episodes": len(shared), "only_a": len(first) - len(shared), "only_b": len(second) - len(shared),
            "overall": _paired(pairs),
            "per_split": {s: _paired([p for p in pairs if p[0]["split"] == s])
                          for s in dict.fromkeys(p[0]["split"] for p in pairs)},
            "per_task_type": {str(t): _paired([p for p in pairs if p[0]["task_type"] == t])
                              for t in sorted({p[0]["task_type"] for p in pairs})},
            "changed": changed}


def _paired(pairs: list[tuple[dict, dict]]) -> dict:
    gained = sum(1 for x, y in pairs if y["success"] and not x["success"])
    lost = sum(1 for x, y in pairs if x["success"] and not y["success"])
    return {"episodes": len(pairs), "a_successes": sum(bool(x["success"]) for x, _ in pairs),
            "b_successes": sum(bool(y["success"]) for _, y in pairs), "gained": gained, "lost": lost,
            "p_value": mcnemar_p(gained, lost)}


def comparison_markdown(comparison: dict, a_label: str, b_label: str, listed: int = 20) -> str:
    """The comparison's tables: overall, per split and per task type, then up to `listed` changed episodes."""
    header = ["", "episodes", "A successes", "B successes", "gained", "lost", "p (exact McNemar)"]

    def row(name: str, entry: dict) -> list[str]:
        return [name, str(entry["episodes"]), str(entry["a_successes"]), str(entry["b_successes"]),
                str(entry["gained"]), str(entry["lost"]), f"{entry['p_value']:.3g}"]

    rows = [row("all", comparison["overall"])]
    rows += [row(SPLIT_TITLES.get(s, s), e) for s, e in comparison["per_split"].items()]
    rows += [row(f"type {t}", e) for t, e in comparison["per_task_type"].items()]
    overall = comparison["overall"]
    lines = [f"A: {a_label}", f"B: {b_label}", "",
             f"{comparison['episodes']} episodes in both runs"
             + (f" ({comparison['only_a']} only in A, {comparison['only_b']} only in B, left out)"
                if comparison["only_a"] or comparison["only_b"] else "")
             + f"; B - A: {overall['b_successes'] - overall['a_successes']:+d} successes "
             f"({overall['gained']} gained, {overall['lost']} lost, p = {overall['p_value']:.3g}).", "",
             markdown_table(header, rows)]
    changed = comparison["changed"]
    if changed:
        lines += ["", f"Changed episodes ({min(listed, len(changed))} of {len(changed)}):", "",
                  markdown_table(["split", "ep_id", "object", "type", "B", "A stopped at", "B stopped at"],
                                 [[c["split"], str(c["ep_id"]), c["obj_id"], str(c["task_type"]),
                                   "gained" if c["b_success"] else "lost", str(c["a_stopped_skill"] or "-"),
                                   str(c["b_stopped_skill"] or "-")] for c in changed[:listed]])]
    return "\n".join(lines)
