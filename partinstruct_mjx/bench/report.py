"""Writes benchmark results into docs/benchmarks.md, one replaceable section per benchmark, and the measured numbers
of a section as JSON in bench_data/<section>.json beside the markdown (read back by `bench/plot.py`)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from partinstruct_mjx.atomic import atomic_write

HEADER = (
    "# Benchmarks\n\n"
    "Every figure here was measured by `partinstruct bench`; each section names its command, machine, versions and "
    "date. Re-running a benchmark replaces its own section and leaves the others alone.\n"
)
DATA_DIR = "bench_data"


def write_section(path: Path, name: str, body: str) -> None:
    """Replace (or append) the section `name` of the markdown file at `path`, atomically."""
    path = Path(path)
    text = path.read_text() if path.exists() else HEADER
    begin, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.DOTALL)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    with atomic_write(path) as file:
        file.write(text)


def provenance_lines(info: dict, command: str) -> str:
    """Markdown lines naming the command, date, commit, machine and versions of a measurement."""
    versions = ", ".join(f"{k} {v}" for k, v in info["versions"].items())
    return (f"- command: `{command}`\n- date: {info['date']}, commit {info['git_sha']}\n"
            f"- machine: {info['machine']}\n- versions: {versions}\n")


def write_report(path: Path, name: str, heading: str, table: str, info: dict, command: str,
                 rows: list[dict] | None = None) -> None:
    """Write the section `name` (heading, provenance, table) and, given `rows`, its data file with the same
    provenance; a suite that produced no rows leaves its data file alone."""
    write_section(path, name, f"## {heading}\n\n" + provenance_lines(info, command) + "\n" + table)
    if rows is not None:
        with atomic_write(data_path(path, name)) as file:
            json.dump({"section": name, "heading": heading, "command": command, "provenance": info, "rows": rows},
                      file, indent=1)
            file.write("\n")


def data_path(markdown: Path, name: str) -> Path:
    """The data file of section `name` of the markdown file `markdown`: bench_data/<name>.json beside it."""
    return Path(markdown).parent / DATA_DIR / f"{name}.json"


def read_data(directory: Path) -> dict[str, dict]:
    """Every data file in `directory` (a bench_data folder), by section name; {} when there is none."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(Path(directory).glob("*.json"))}


def env_row(series: str | None, batch_size: int, per_s: float, spread: tuple[float, float], **fields) -> dict:
    """One measured row as the data files keep it: env steps/s (median) and its range over repeats at a batch size,
    the plot's series label (None: not plotted) and any other fields of the row."""
    return {"series": series, "batch_size": batch_size, "env_steps_per_s": per_s, "range": list(spread), **fields}
