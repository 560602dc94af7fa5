"""Writes benchmark results into docs/benchmarks.md, one replaceable section per benchmark."""

from __future__ import annotations

import re
from pathlib import Path

from partinstruct_mjx.atomic import atomic_write

HEADER = (
    "# Benchmarks\n\n"
    "Every figure here was measured by `partinstruct bench`; each section names its command, machine, versions and "
    "date. Re-running a benchmark replaces its own section and leaves the others alone.\n"
)


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
