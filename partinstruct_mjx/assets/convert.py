"""PartNet-Mobility folders -> assets_mjcf/objects/<category>/<id>/ (object.xml, meshes/, parts.npz, meta.json).

Safe at scale: objects whose sources and settings are unchanged are skipped; decompositions are cached by content
hash and run on a process pool with a per-mesh time limit; each object is written to a temporary folder and
swapped in only when complete, so a failure leaves no partial folder and never destroys a previous conversion.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from tqdm import tqdm

from partinstruct_mjx.assets.catalog import update_catalog
from partinstruct_mjx.assets.decompose import (CONVERTER_VERSION, DecompositionConfig, HullCache, decompose,
                                               decomposition_key, hull_budgets, separate_sources,
                                               single_hull_gap)
from partinstruct_mjx.assets.geometry import AssembledObject, assemble
from partinstruct_mjx.assets.mjcf import MJCF_VERSION, PhysicsConfig, write_mjcf
from partinstruct_mjx.assets.partnet import PartNetObject, category_slug, is_semantic_label, read_partnet_object
from partinstruct_mjx.assets.surface import sample_parts
from partinstruct_mjx.assets.timeout_pool import run_jobs
from partinstruct_mjx.errors import AssetError

DEFAULT_CACHE_DIR = Path.home() / ".cache" / "partinstruct_mjx" / "coacd"


@dataclass(frozen=True)
class ConvertConfig:
    """Everything that decides a conversion's output (and the run's resources).

    Attributes:
      scale: multiply the dataset's units by this; overrides `target_size`.
      target_size: scale each object so its largest extent is this many metres (PartNet meshes are unit-sized).
      rigid: freeze every joint (one rigid body).
      points_per_part, object_points, seed: surface samples written to parts.npz.
      workers, timeout: decomposition processes and the per-mesh time limit in seconds.
    """

    scale: float | None = None
    target_size: float | None = 0.2
    rigid: bool = False
    physics: PhysicsConfig = PhysicsConfig()
    decomposition: DecompositionConfig = DecompositionConfig()
    points_per_part: int = 2048
    object_points: int = 4096
    seed: int = 0
    workers: int = max(1, os.cpu_count() or 1)
    timeout: float = 900.0
    cache_dir: str = str(DEFAULT_CACHE_DIR)

    def output_settings(self) -> dict:
        """The settings that change the output (not workers, timeout or cache location)."""
        settings = dataclasses.asdict(self)
        for key in ("workers", "timeout", "cache_dir"):
            settings.pop(key)
        return settings


@dataclass
class ConversionRecord:
    source: Path
    object_id: str = "?"
    category: str = "?"
    status: str = "pending"
    """'converted', 'cached' or 'failed'."""
    reason: str = ""
    hulls: int = 0
    vertices: int = 0
    seconds: float = 0.0
    output: Path | None = None


@dataclass
class _Job:
    record: ConversionRecord
    obj: PartNetObject
    assembled: AssembledObject
    output: Path
    source_hash: str
    budgets: list[int]
    keys: list[str]
    prepare_seconds: float = 0.0


def find_object_folders(paths: list[str | os.PathLike]) -> list[Path]:
    """Object folders (those holding mobility.urdf) among `paths` and below them."""
    folders = []
    for path in map(Path, paths):
        if (path / "mobility.urdf").is_file():
            folders.append(path)
        elif path.is_dir():
            folders.extend(sorted(p.parent for p in path.rglob("mobility.urdf")))
        else:
            raise AssetError(f"not a folder: {path}")
    if not folders:
        raise AssetError(f"no PartNet-Mobility object (mobility.urdf) under {', '.join(map(str, paths))}")
    return folders


def convert_objects(sources: list[str | os.PathLike], out_root: str | os.PathLike, config: ConvertConfig = ConvertConfig(),
                    progress: bool = True) -> list[ConversionRecord]:
    """Convert every object folder under `sources` into `out_root`; returns one record per object."""
    out_root = Path(out_root)
    cache = HullCache(config.cache_dir)
    records, jobs = [], []
    for folder in find_object_folders(sources):
        record = ConversionRecord(source=folder)
        records.append(record)
        job = _prepare(record, out_root, config)
        if job is not None:
            jobs.append(job)
    _decompose_missing(jobs, cache, config, progress)
    for job in tqdm(jobs, desc="writing", unit="object", disable=not progress or not jobs):
        if job.record.status != "failed":
            _write_object(job, cache, out_root, config)
    return records


def summary_table(records: list[ConversionRecord]) -> str:
    """A plain-text table of every object's outcome, then the totals."""
    lines = [f"{'object':<28} {'category':<14} {'status':<10} {'hulls':>5} {'verts':>6} {'seconds':>8}  reason"]
    for r in records:
        lines.append(f"{r.object_id:<28} {r.category:<14} {r.status:<10} {r.hulls:>5} {r.vertices:>6} "
                     f"{r.seconds:>8.1f}  {r.reason}")
    counts = {s: sum(r.status == s for r in records) for s in ("converted", "cached", "failed")}
    lines.append(", ".join(f"{n} {s}" for s, n in counts.items()))
    return "\n".join(lines)


def source_hash(obj: PartNetObject, config: ConvertConfig) -> str:
    """Hash of every input file and every output-relevant setting."""
    digest = hashlib.sha256(json.dumps([CONVERTER_VERSION, MJCF_VERSION, config.output_settings()],
                                       sort_keys=True).encode())
    for path in obj.source_files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _prepare(record: ConversionRecord, out_root: Path, config: ConvertConfig) -> _Job | None:
    started = time.perf_counter()
    try:
        obj = read_partnet_object(record.source)
        record.object_id, record.category = obj.object_id, category_slug(obj.category)
        output = out_root / "objects" / record.category / obj.object_id
        digest = source_hash(obj, config)
        previous = _read_meta(output)
        if previous.get("source_hash") == digest:
            record.status, record.output = "cached", output
            record.hulls, record.vertices = previous["stats"]["hulls"], previous["stats"]["hull_vertices"]
            update_catalog(out_root, [_catalog_entry(previous)])
            return None
        assembled = assemble(obj, config.scale, config.target_size, config.rigid)
        gaps = [single_hull_gap(p.vertices, p.faces) for p in assembled.collision]
        units, gaps = separate_sources(assembled.collision, gaps, config.decomposition.max_hulls_per_object)
        assembled = dataclasses.replace(assembled, collision=units)
        areas = [trimesh.Trimesh(p.vertices, p.faces, process=False).area for p in assembled.collision]
        budgets = hull_budgets(areas, config.decomposition, gaps)
        keys = [decomposition_key(p.vertices, p.faces, b, config.decomposition)
                for p, b in zip(assembled.collision, budgets)]
    except AssetError as err:
        record.status, record.reason = "failed", str(err)
        return None
    return _Job(record, obj, assembled, output, digest, budgets, keys, time.perf_counter() - started)


def _decompose_job(vertices: np.ndarray, faces: np.ndarray, budget: int, config: DecompositionConfig):
    start = time.perf_counter()
    hulls = decompose(vertices, faces, budget, config)
    return hulls, time.perf_counter() - start


def _decompose_missing(jobs: list[_Job], cache: HullCache, config: ConvertConfig, progress: bool) -> None:
    """Run every decomposition not in the cache; mark the objects whose part failed or timed out."""
    todo: dict[str, tuple] = {}
    owners: dict[str, list[tuple[_Job, str]]] = {}
    for job in jobs:
        for piece, budget, key in zip(job.assembled.collision, job.budgets, job.keys):
            owners.setdefault(key, []).append((job, piece.part))
            if key not in todo and cache.get(key) is None:
                todo[key] = (piece.vertices, piece.faces, budget, config.decomposition)
    trivial = [k for k, args in todo.items() if args[2] == 1]
    for key in trivial:
        hulls, seconds = _decompose_job(*todo.pop(key))
        cache.put(key, hulls, seconds)
    if not todo:
        return
    bar = tqdm(total=len(todo), desc="decomposing", unit="part", disable=not progress)
    for result in run_jobs(_decompose_job, list(todo.items()), config.workers, config.timeout):
        bar.update()
        if result.error is None:
            cache.put(result.key, *result.value)
            continue
        for job, part in owners[result.key]:
            job.record.status = "failed"
            job.record.reason = f"part '{part}': CoACD {result.error}"
    bar.close()


def _write_object(job: _Job, cache: HullCache, out_root: Path, config: ConvertConfig) -> None:
    record, output = job.record, job.output
    started = time.perf_counter()
    temporary = output.parent / f".{output.name}.tmp-{os.getpid()}"
    shutil.rmtree(temporary, ignore_errors=True)
    try:
        cached = [cache.get_with_seconds(key) for key in job.keys]
        hulls = [h for h, _ in cached]
        temporary.mkdir(parents=True)
        stats = write_mjcf(temporary, job.obj.object_id, job.assembled, hulls, config.physics)
        try:
            mujoco.MjModel.from_xml_path(str(temporary / "object.xml"))
        except ValueError as err:
            raise AssetError(f"the written MJCF does not compile: {err}") from err
        np.savez_compressed(temporary / "parts.npz", **sample_parts(
            job.assembled, config.points_per_part, config.object_points, config.seed))
        stats["decomposition_seconds"] = round(sum(s for _, s in cached), 2)
        own_seconds = job.prepare_seconds + time.perf_counter() - started
        stats["seconds"] = round(own_seconds + stats["decomposition_seconds"], 2)
        meta = _meta(job, hulls, stats, config)
        (temporary / "meta.json").write_text(json.dumps(meta, indent=1) + "\n")
        _swap_in(temporary, output)
    except (AssetError, OSError) as err:
        shutil.rmtree(temporary, ignore_errors=True)
        record.status, record.reason = "failed", str(err)
        return
    record.status, record.output = "converted", output
    record.hulls, record.vertices, record.seconds = stats["hulls"], stats["hull_vertices"], stats["seconds"]
    update_catalog(out_root, [_catalog_entry(meta)])


def _swap_in(temporary: Path, output: Path) -> None:
    """Replace `output` by `temporary` so that readers see either the old or the new folder, never a mix."""
    if output.exists():
        retired = output.parent / f".{output.name}.old-{os.getpid()}"
        os.rename(output, retired)
        os.rename(temporary, output)
        shutil.rmtree(retired)
    else:
        os.rename(temporary, output)


def _meta(job: _Job, hulls, stats: dict, config: ConvertConfig) -> dict:
    obj, assembled = job.obj, job.assembled
    parts = []
    for label in dict.fromkeys(p.part for p in assembled.collision):
        indices = [i for i, p in enumerate(assembled.collision) if p.part == label]
        parts.append({"name": label, "semantic": is_semantic_label(label),
                      "bodies": sorted({assembled.collision[i].body for i in indices}),
                      "hulls": sum(len(hulls[i]) for i in indices)})
    joints = [{"name": b.joint.name, "type": b.joint.kind, "body": b.name,
               "range": None if b.joint.range is None else [float(v) for v in b.joint.range]}
              for b in assembled.bodies if b.joint is not None]
    return {
        "id": obj.object_id,
        "category": category_slug(obj.category),
        "model_cat": obj.category,
        "parts": parts,
        "joints": joints,
        "scale": assembled.scale,
        "mass": stats.pop("mass"),
        "source": {"folder": _display_path(obj.folder), "files": {str(p.relative_to(obj.folder)): _sha256(p)
                                                       for p in obj.source_files}},
        "source_hash": job.source_hash,
        "converter_version": CONVERTER_VERSION,
        "mjcf_version": MJCF_VERSION,
        "conversion": config.output_settings(),
        "stats": stats,
    }


def _catalog_entry(meta: dict) -> dict:
    return {"id": meta["id"], "category": meta["category"], "path": f"objects/{meta['category']}/{meta['id']}",
            "parts": [p["name"] for p in meta["parts"] if p["semantic"]], "scale": meta["scale"],
            "source": meta["source"]["folder"], "splits": []}


def _read_meta(output: Path) -> dict:
    try:
        return json.loads((output / "meta.json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def _display_path(path: Path) -> str:
    """`path` relative to the working directory when it lies inside it (no machine-specific prefixes)."""
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
