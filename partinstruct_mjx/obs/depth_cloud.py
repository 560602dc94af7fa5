"""Camera observations of spec 2.1 from OpenGL depth and segmentation: scene and part point clouds, part masks.

The original's pipeline: back-project the static camera's robot and object pixels (background, floor and table
dropped, depth truncated at 3 m) with K into the camera optical frame, then farthest-point sample 1024 points from
a deterministic start (PyTorch3D, index 0). Rays pass through pixel centres (u + 0.5, v + 0.5), as OpenGL renders
them; the original's Open3D back-projection used (u, v), a half-pixel shift (~2 mm at 1 m). Farthest-point
sampling runs in NumPy: on this 2-core CPU it takes ~7 ms for 5,000 points (about what the robot and object
cover), where a jitted JAX loop takes as long at 5,000 points and 10-20x longer at 10,000-20,000.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.obs.cameras import AGENTVIEW, PCD_SIZE, WRIST, optical_to_world, world_to_optical
from partinstruct_mjx.obs.images import CameraImages, ImageRenderer, backproject
from partinstruct_mjx.sim.state import SceneState

DEPTH_TRUNCATION = 3.0
"""Metres; farther pixels are dropped (the original's Open3D `depth_trunc`)."""


def farthest_point_sample(points: np.ndarray, count: int) -> np.ndarray:
    """Indices (count,) of a farthest-point sample of points (N, 3), starting at index 0.

    With exactly `count` points all are taken in stored order (the same set, without the O(N count) search);
    with fewer, the sample repeats point 0 once every point is taken; with none it is empty.
    """
    if len(points) in (0, count):
        return np.arange(len(points))
    coords = [np.ascontiguousarray(points[:, k], dtype=np.float32) for k in range(3)]
    nearest = np.full(len(points), np.inf, np.float32)
    squared, term = np.empty_like(nearest), np.empty_like(nearest)
    chosen = np.zeros(count, np.int64)
    last = 0
    for i in range(1, min(count, len(points))):
        np.subtract(coords[0], coords[0][last], out=squared)
        np.multiply(squared, squared, out=squared)
        for axis in coords[1:]:
            np.subtract(axis, axis[last], out=term)
            np.multiply(term, term, out=term)
            squared += term
        np.minimum(nearest, squared, out=nearest)
        chosen[i] = last = int(nearest.argmax())
    return chosen


def scene_cloud(renderer: ImageRenderer, images: CameraImages,
                count: int = PCD_SIZE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Farthest-point sample of the robot and object pixels, back-projected.

    Returns:
      Optical-frame points (count, 3) float32 (zeros when nothing is in view) and the sampled pixels' (rows, cols).
    """
    keep = renderer.robot_or_object(images.segmentation) & (images.depth < DEPTH_TRUNCATION)
    rows, cols = np.nonzero(keep)
    points = backproject(images.depth[rows, cols], rows, cols, images.intrinsics).astype(np.float32)
    chosen = farthest_point_sample(points, count)
    if len(chosen) == 0:
        return np.zeros((count, 3), np.float32), np.zeros(count, np.int64), np.zeros(count, np.int64)
    return points[chosen], rows[chosen], cols[chosen]


def camera_observations(renderer: ImageRenderer, state: SceneState | np.ndarray, target_part: int | None,
                        masks: jnp.ndarray, wrist: bool = False) -> dict[str, np.ndarray]:
    """Spec 2.1's camera observations of one scene (a SceneState row), plus world-frame clouds and camera matrices.

    Images are HWC (H, W, 3): the original's env returned CHW, but its demos and loaders hold HWC (spec 9.3).

    Args:
      renderer: the scene's ImageRenderer (its size sets H and W; the benchmark's is 300 x 300).
      state: one scene's SceneState row (only its qpos is read: poses are recomputed for rendering).
      target_part: part row of the current skill's target (PartGeometry.index), or None when it has none.
      masks: (7, M) spatial-part masks of this scene (TaskState.masks[b]).
      wrist: add the wrist camera's keys.
    Returns:
      agentview_rgb (H, W, 3) uint8; agentview_pcd (1024, 3) optical frame and agentview_pcd_world (1024, 3);
      agentview_part_pcd (1024, 4) (points + 1 where the point's pixel is in the part mask); agentview_part_mask
      (H, W) uint8; agentview_intrinsics (3, 3); agentview_extrinsics (4, 4) world -> optical frame. With wrist:
      wrist_rgb, wrist_part_pcd (1024, 3: the target part's points in the wrist optical frame, unoccluded, zeros
      without a part) and wrist_part_pcd_world, wrist_part_mask, wrist_intrinsics, wrist_extrinsics.
    """
    images = renderer.render(state, AGENTVIEW)
    mask = renderer.part_mask(images, target_part, masks)
    points, rows, cols = scene_cloud(renderer, images)
    obs = {
        "agentview_rgb": images.rgb,
        "agentview_pcd": points,
        "agentview_pcd_world": np.asarray(optical_to_world(points, images.position, images.rotation), np.float32),
        "agentview_part_pcd": np.concatenate([points, mask[rows, cols, None].astype(np.float32)], axis=1),
        "agentview_part_mask": mask,
        "agentview_intrinsics": images.intrinsics,
        "agentview_extrinsics": images.world_to_camera,
    }
    if wrist:
        obs |= _wrist_observations(renderer, state, target_part, masks)
    return obs


def _wrist_observations(renderer: ImageRenderer, state: SceneState | np.ndarray, target_part: int | None,
                        masks: jnp.ndarray) -> dict[str, np.ndarray]:
    images = renderer.render(state, WRIST, depth_segmentation=target_part is not None)
    world = np.zeros((PCD_SIZE, 3), np.float32)
    optical = world.copy()
    if target_part is not None:
        cloud, valid = renderer.part_cloud(images, target_part, masks)
        cloud = cloud[valid]
        if len(cloud):
            world = cloud[farthest_point_sample(cloud, PCD_SIZE)].astype(np.float32)
            optical = np.asarray(world_to_optical(world, images.position, images.rotation), np.float32)
    return {
        "wrist_rgb": images.rgb,
        "wrist_part_pcd": optical,
        "wrist_part_pcd_world": world,
        "wrist_part_mask": renderer.part_mask(images, target_part, masks),
        "wrist_intrinsics": images.intrinsics,
        "wrist_extrinsics": images.world_to_camera,
    }
