"""Aggregates of per-episode evaluation records and their markdown tables (the paper's layout, spec 9.4 / Table 1).

Rates are fractions in the JSON and percentages in the tables. A rate's standard error is that of a mean over
rollouts, sqrt(p (1 - p) / n) (population variance): it reproduces the paper's error bars (51 of 220 rollouts:
23.18 +- 2.8). 'All' pools every episode; the mean of the split rates is given beside it.
"""

from __future__ import annotations

import math
from collections import defaultdict

from partinstruct_mjx.eval.config import SPLIT_TITLES
from partinstruct_mjx.tasks.skills import SKILL_NAMES

WHOLE_OBJECT = "(whole object)"
"""Label of the part '' (the whole object) in the per-part aggregates."""


def mean_se(values) -> tuple[float | None, float | None]:
    """Mean of `values` and its standard error sqrt(var / n) (population variance); (None, None) when empty."""
    values = [float(v) for v in values]
    if not values:
        return None, None
    mean = sum(values) / len(values)
    variance = sum((v - mean) ** 2 for v in values) / len(values)
    return mean, math.sqrt(variance / len(values))


def rates(records: list[dict]) -> dict:
    """Episodes, successes, success rate and completion rate (each with its standard error) of some records."""
    success, success_se = mean_se(r["success"] for r in records)
    completion, completion_se = mean_se(r["completion"] for r in records)
    return {"episodes": len(records), "successes": sum(bool(r["success"]) for r in records),
            "success_rate": success, "success_se": success_se,
            "completion_rate": completion, "completion_se": completion_se}


def aggregate(records: list[dict], splits: list[str] | None = None) -> dict:
    """Every aggregate of results.json: overall (all episodes pooled), per split (in `splits` order, default as they
    occur), the mean of the split rates, per task type, per category, per target part (episodes whose chain names
    the part) and per skill (of the chain skills an episode reached, the share completed)."""
    splits = splits or list(dict.fromkeys(r["split"] for r in records))
    per_split = {s: rates([r for r in records if r["split"] == s]) for s in splits}
    evaluated = [v for v in per_split.values() if v["episodes"]]
    by_part, by_skill = defaultdict(list), defaultdict(lambda: [0, 0])
    for r in records:
        for part in dict.fromkeys(r["target_parts"]):
            by_part[part or WHOLE_OBJECT].append(r)
        completed = sum(r["skill_success"])
        for i, (name, done) in enumerate(zip(r["skills"], r["skill_success"])):
            if i <= completed:
                by_skill[name][0] += 1
                by_skill[name][1] += bool(done)
    return {
        "overall": rates(records),
        "physics_unstable": sum(bool(r.get("physics_unstable")) for r in records),
        "per_split": per_split,
        "mean_over_splits": {key: sum(v[key] for v in evaluated) / len(evaluated) if evaluated else None
                             for key in ("success_rate", "completion_rate")},
        "per_task_type": {str(t): rates([r for r in records if r["task_type"] == t])
                          for t in sorted({r["task_type"] for r in records})},
        "per_category": {c: rates([r for r in records if r["category"] == c])
                         for c in sorted({r["category"] for r in records})},
        "per_part": {p: rates(by_part[p]) for p in sorted(by_part)},
        "per_skill": {name: {"reached": reached, "completed": completed, "success_rate": completed / reached}
                      for name, (reached, completed) in sorted(by_skill.items(), key=lambda i: _skill_rank(i[0]))},
    }


def _skill_rank(name: str) -> tuple[int, str]:
    """Skills in the order of SKILL_NAMES (grasp, touch, move, rotate, release)."""
    return (SKILL_NAMES.index(name), name) if name in SKILL_NAMES else (len(SKILL_NAMES), name)


def percent(rate: float | None, se: float | None = None) -> str:
    """'23.18 ± 2.8' (percent, the paper's precision); '-' for no episodes."""
    if rate is None:
        return "-"
    return f"{100 * rate:.2f}" + ("" if se is None else f" ± {100 * se:.1f}")


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def success_table(summary: dict, splits: list[str], label: str) -> str:
    """The paper's Table 1 layout: one row, success rate ± standard error per split and All (pooled)."""
    cells = [percent(summary["per_split"][s]["success_rate"], summary["per_split"][s]["success_se"]) for s in splits]
    overall = summary["overall"]
    return markdown_table(["Policy", *(SPLIT_TITLES[s] for s in splits), "All"],
                          [[label, *cells, percent(overall["success_rate"], overall["success_se"])]])


def split_table(summary: dict, splits: list[str]) -> str:
    """Per split: episodes, successes, success and completion rates with standard errors."""
    rows = [[SPLIT_TITLES[s], *_counts(summary["per_split"][s])] for s in splits]
    rows.append(["All", *_counts(summary["overall"])])
    return markdown_table(["split", "episodes", "successes", "success %", "completion %"], rows)


def _counts(entry: dict) -> list[str]:
    return [str(entry["episodes"]), str(entry["successes"]), percent(entry["success_rate"], entry["success_se"]),
            percent(entry["completion_rate"], entry["completion_se"])]


def results_markdown(results: dict) -> str:
    """results.md: the success table, the per-split, per-type, per-skill, per-part and per-category tables."""
    summary, config = results["summary"], results["config"]
    splits = [s for s in config["splits"] if summary["per_split"].get(s, {}).get("episodes")]
    mean = summary["mean_over_splits"]
    provenance = results["provenance"]
    lines = [
        f"# Evaluation: {results['label']}", "",
        f"- policy: {config['policy']}; planner: {config['planner'] or 'none'}"
        + (f" (every {config['planner_every']} steps)" if config["planner"] else "")
        + f"; {config['mode']} mode; backend {config['backend']}; seed {config['seed']}",
        f"- episodes: {summary['overall']['episodes']}" + ("" if results["complete"] else " (run not complete)")
        + f"; step limits: {', '.join(f'{s} {n}' for s, n in results['resolved']['step_limits'].items())}",
        f"- {provenance['date']}, commit {provenance['git_sha']}, {provenance['machine']}",
        *([f"- {summary['physics_unstable']} episodes ended early, failed, because their simulation diverged "
           "(NaN or huge joint values; `physics_unstable` in results.json)"]
          if summary.get("physics_unstable") else []),
        "",
        "## Success rate (%) ± standard error", "", success_table(summary, splits, results["label"]), "",
        f"Mean of the split rates: success {percent(mean['success_rate'])} %, completion "
        f"{percent(mean['completion_rate'])} %.", "",
        "## Per split", "", split_table(summary, splits), "",
        "## Per task type", "",
        markdown_table(["type", "episodes", "successes", "success %", "completion %"],
                       [[t, *_counts(e)] for t, e in summary["per_task_type"].items()]), "",
        "## Per skill (of the chain skills reached, the share completed)", "",
        markdown_table(["skill", "reached", "completed", "success %"],
                       [[name, str(e["reached"]), str(e["completed"]), percent(e["success_rate"])]
                        for name, e in summary["per_skill"].items()]), "",
        "## Per target part (episodes whose chain names the part)", "",
        markdown_table(["part", "episodes", "successes", "success %", "completion %"],
                       [[p, *_counts(e)] for p, e in summary["per_part"].items()]), "",
        "## Per category", "",
        markdown_table(["category", "episodes", "successes", "success %", "completion %"],
                       [[c, *_counts(e)] for c, e in summary["per_category"].items()]), "",
    ]
    return "\n".join(lines)
