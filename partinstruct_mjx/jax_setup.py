"""JAX settings the project relies on: the CPU fusion flag (set before JAX loads) and the compilation cache."""

from __future__ import annotations

import importlib.metadata
import os
from pathlib import Path

CPU_FUSION_FLAG = "--xla_cpu_use_fusion_emitters=false"
"""22x faster MJX / kinematics-heavy steps on a CPU with jax 0.10 (see DESIGN.md)."""
FLAG_JAXLIB_VERSIONS = ((0, 5), (0, 11))
"""jaxlib versions [from, to) that know the flag; jax 0.11 aborts on it as an unknown flag."""

DEFAULT_CACHE_DIR = Path.home() / ".cache" / "partinstruct_mjx" / "jax"


def _jaxlib_version() -> tuple[int, int] | None:
    try:
        major, minor = importlib.metadata.version("jaxlib").split(".")[:2]
        return int(major), int(minor)
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None


def set_xla_flags() -> None:
    """Add the CPU fusion flag to XLA_FLAGS (jaxlib versions that know it, unless the user chose a value)."""
    version = _jaxlib_version()
    if version is None or not FLAG_JAXLIB_VERSIONS[0] <= version < FLAG_JAXLIB_VERSIONS[1]:
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {CPU_FUSION_FLAG}".strip()


def enable_compilation_cache(cache_dir: str | os.PathLike | None = None) -> Path:
    """Turn on JAX's persistent compilation cache ($PARTINSTRUCT_JAX_CACHE or ~/.cache/partinstruct_mjx/jax)."""
    import jax

    path = Path(cache_dir or os.environ.get("PARTINSTRUCT_JAX_CACHE", DEFAULT_CACHE_DIR))
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path
