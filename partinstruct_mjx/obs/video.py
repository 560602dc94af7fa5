"""Stored trajectories (a .npz of qpos per step) and their H.264 videos from the static and wrist cameras.

A trajectory file holds `qpos` (T, nq), `object_xml` (the object MJCF, relative to the assets root when it lies
inside it, else absolute) and optionally `part` (T,) with each step's target part (a name `PartGeometry.index`
accepts: a semantic label, a spatial word, '' for the whole object; NO_PART for none), which the video tints.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from partinstruct_mjx.atomic import atomic_path, atomic_write
from partinstruct_mjx.errors import AssetError, PartInstructError, SceneError
from partinstruct_mjx.obs.cameras import AGENTVIEW, IMAGE_SIZE, WRIST
from partinstruct_mjx.obs.images import ImageRenderer
from partinstruct_mjx.paths import assets_root
from partinstruct_mjx.sim.scene import Scene, SceneConfig, build_scene
from partinstruct_mjx.tasks.part_geometry import spatial_masks
from partinstruct_mjx.tasks.predicates import object_points

NO_PART = "<none>"
"""`part` entry of a step without a target part."""
PART_TINT = np.array([40, 220, 90], np.float32)
"""Colour blended over the target part's pixels (half and half)."""


@dataclass(frozen=True)
class Trajectory:
    """Configurations to render. `source` names where it came from, for error messages."""

    qpos: np.ndarray
    object_xml: Path
    part: tuple[str, ...] | None = None
    source: str = "<trajectory>"


def save_trajectory(path: str | os.PathLike, scene: Scene, qpos: np.ndarray, part: list[str] | None = None) -> None:
    """Write a trajectory of `scene` atomically; SceneError if qpos is not (T, nq) or `part` is not one per step."""
    qpos = np.asarray(qpos, dtype=float)
    if qpos.ndim != 2 or qpos.shape[1] != scene.model.nq or len(qpos) == 0:
        raise SceneError(f"{path}: qpos must have shape (T >= 1, {scene.model.nq}), got {qpos.shape}")
    arrays = {"qpos": qpos, "object_xml": np.array(_stored_xml(scene.object_xml))}
    if part is not None:
        if len(part) != len(qpos):
            raise SceneError(f"{path}: {len(part)} part names for {len(qpos)} steps")
        arrays["part"] = np.array(part, dtype=str)
    with atomic_write(path, "wb") as file:
        np.savez_compressed(file, **arrays)


def load_trajectory(path: str | os.PathLike) -> Trajectory:
    """Read a trajectory file; SceneError naming the file and what is missing or malformed."""
    arrays = _read_npz(path)
    missing = [key for key in ("qpos", "object_xml") if key not in arrays]
    if missing:
        raise SceneError(f"{path}: missing {' and '.join(missing)}")
    qpos, xml = arrays["qpos"], arrays["object_xml"]
    if qpos.ndim != 2 or len(qpos) == 0 or not np.issubdtype(qpos.dtype, np.number):
        raise SceneError(f"{path}: qpos must be a numeric (T >= 1, nq) array, got {qpos.dtype} {qpos.shape}")
    if xml.ndim != 0 or xml.dtype.kind != "U":
        raise SceneError(f"{path}: object_xml must be one string")
    object_xml = _resolve_xml(str(xml))
    if not object_xml.is_file():
        raise SceneError(f"{path}: object MJCF {object_xml} not found")
    part = arrays.get("part")
    if part is not None and (part.shape != (len(qpos),) or part.dtype.kind != "U"):
        raise SceneError(f"{path}: part must hold one string per step ({len(qpos)}), got {part.dtype} {part.shape}")
    return Trajectory(qpos.astype(float), object_xml, None if part is None else tuple(part.tolist()), str(path))


def _read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise SceneError(f"trajectory file not found: {path}") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise SceneError(f"{path}: not a trajectory .npz file ({err})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise SceneError(f"{path}: not a trajectory .npz file (it holds a single array)")
    with data:
        try:
            return {key: data[key] for key in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
            raise SceneError(f"{path}: unreadable array in the trajectory file ({err})") from None


def render_video(trajectory: Trajectory | str | os.PathLike, out_mp4: str | os.PathLike, wrist: bool = False,
                 fps: int = 20, progress: bool = False) -> int:
    """Render every step from the static camera (and the wrist camera beside it) to an H.264 MP4, atomically.

    Returns the number of frames. SceneError if the qpos width does not match the trajectory's object.
    """
    from imageio_ffmpeg import write_frames

    if fps < 1:
        raise SceneError(f"fps must be at least 1, got {fps}")
    if not isinstance(trajectory, Trajectory):
        trajectory = load_trajectory(trajectory)
    scene = _scene(trajectory)
    with atomic_path(out_mp4) as temporary:
        # ffmpeg starts before the renderer initialises JAX, which warns about any later fork.
        writer = write_frames(str(temporary), (IMAGE_SIZE * (2 if wrist else 1), IMAGE_SIZE), fps=fps,
                              codec="libx264", pix_fmt_out="yuv420p", macro_block_size=1, ffmpeg_log_level="error")
        try:
            writer.send(None)
            with ImageRenderer(scene) as renderer:
                for step in tqdm(range(len(trajectory.qpos)), desc="render", unit="frame", disable=not progress):
                    views = [_frame(renderer, trajectory, step, AGENTVIEW)]
                    if wrist:
                        views.append(_frame(renderer, trajectory, step, WRIST))
                    writer.send(np.ascontiguousarray(np.concatenate(views, axis=1)))
        finally:
            writer.close()
    return len(trajectory.qpos)


def _frame(renderer: ImageRenderer, trajectory: Trajectory, step: int, camera: str) -> np.ndarray:
    """RGB of one step, with the step's target part tinted when the trajectory names one."""
    part = trajectory.part[step] if trajectory.part else NO_PART
    images = renderer.render(trajectory.qpos[step], camera, depth_segmentation=part != NO_PART)
    if part == NO_PART:
        return images.rgb
    geometry = renderer.geometry
    try:
        row = renderer.part_names.index(part)
    except PartInstructError as err:
        raise SceneError(f"{trajectory.source}: step {step}: {err}") from None
    # Spatial parts as sampled from this step's pose (the env samples them when a skill starts).
    masks = spatial_masks(object_points(images, geometry))
    mask = renderer.part_mask(images, row, masks).astype(bool)
    rgb = images.rgb.astype(np.float32)
    rgb[mask] = 0.5 * rgb[mask] + 0.5 * PART_TINT
    return rgb.astype(np.uint8)


def _scene(trajectory: Trajectory) -> Scene:
    try:
        scene = build_scene(SceneConfig(object_xml=str(trajectory.object_xml)))
    except AssetError as err:
        raise SceneError(f"{trajectory.source}: {err}") from None
    if trajectory.qpos.shape[1] != scene.model.nq:
        raise SceneError(f"{trajectory.source}: qpos has {trajectory.qpos.shape[1]} columns but the scene with "
                         f"{trajectory.object_xml} has nq = {scene.model.nq}")
    return scene


def _stored_xml(object_xml: Path) -> str:
    """The object MJCF relative to the assets root when inside it (portable between checkouts), else absolute."""
    path = Path(object_xml).resolve()
    try:
        return path.relative_to(assets_root().resolve()).as_posix()
    except ValueError:
        return str(path)


def _resolve_xml(stored: str) -> Path:
    path = Path(stored)
    return path if path.is_absolute() else assets_root() / path
