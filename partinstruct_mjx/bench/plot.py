"""Env steps/s against batch size (log-log), one line per measured series, drawn from the benchmarks' data files.

Every row of docs/bench_data/*.json with a series label is a point; the suites that write them are cpu_backend,
pybullet and mjx (`partinstruct bench ...`). Needs matplotlib (`pip install -e .[bench]`).

    python -m partinstruct_mjx.bench.plot            # docs/bench_data -> docs/env_steps_vs_batch.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

from partinstruct_mjx.atomic import atomic_path
from partinstruct_mjx.bench.report import DATA_DIR, read_data
from partinstruct_mjx.errors import PartInstructError

DEFAULT_DATA = Path("docs") / DATA_DIR
DEFAULT_OUTPUT = Path("docs/env_steps_vs_batch.png")
TARGET = (4096, 100_000)
"""DESIGN.md's MJX target: 100,000 env steps/s at batch 4,096 (one H100)."""


def series(data: dict[str, dict]) -> dict[str, list[tuple[int, float, float, float]]]:
    """(batch, median, slowest, fastest) per series label, sorted by batch, from `read_data`'s sections."""
    points: dict[str, list[tuple[int, float, float, float]]] = {}
    for section in data.values():
        for row in section["rows"]:
            if row.get("series") and row.get("env_steps_per_s") is not None:
                points.setdefault(row["series"], []).append(
                    (row["batch_size"], row["env_steps_per_s"], *row["range"]))
    return {label: sorted(p) for label, p in points.items()}


def plot(data_dir: Path = DEFAULT_DATA, output: Path = DEFAULT_OUTPUT) -> Path:
    """Draw every series of the data files in `data_dir` into the PNG `output` (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    lines = series(read_data(data_dir))
    if not lines:
        raise PartInstructError(f"{data_dir}: no data files with env steps/s rows; run `partinstruct bench` "
                                f"(cpu_backend, pybullet, mjx) first")
    figure, axes = plt.subplots(figsize=(8.5, 5.5))
    for label, points in lines.items():
        batch, median, slowest, fastest = zip(*points)
        axes.errorbar(batch, median, yerr=[[m - s for m, s in zip(median, slowest)],
                                           [f - m for m, f in zip(median, fastest)]],
                      marker="o", capsize=3, label=label)
    axes.plot(*TARGET, marker="*", markersize=14, color="black", linestyle="none",
              label="target: 100,000 env steps/s at batch 4,096 (one H100)")
    axes.set_xscale("log", base=4)
    axes.set_yscale("log")
    axes.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: f"{x:,.0f}"))
    axes.set_xlabel("batch size (environments stepped together)")
    axes.set_ylabel("env steps/s (median; bars: range over repeats)")
    axes.set_title("PartInstruct env steps/s vs batch size (measured, docs/benchmarks.md)")
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7, loc="best")
    figure.tight_layout()
    with atomic_path(output) as temporary:
        figure.savefig(temporary, dpi=120)
    plt.close(figure)
    return Path(output)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help=f"data folder (default {DEFAULT_DATA})")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT, help=f"PNG (default {DEFAULT_OUTPUT})")
    args = parser.parse_args(argv)
    try:
        print(f"wrote {plot(args.data, args.output)}")
    except PartInstructError as err:
        print(f"error: {err}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
