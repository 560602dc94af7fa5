"""OpenGL images of one scene state: RGB, metric depth, geom segmentation, and target-part masks with occlusion.

MuJoCo's offscreen renderer with cheap visual settings (no MSAA, shadows or reflections), which on Mesa llvmpipe
renders 300x300 RGB several times faster than the default (DESIGN.md "Rendering on a CPU"). Depth and segmentation
come from one pass (the segmentation pass fills the depth buffer too), ~1.8x cheaper than `mujoco.Renderer`'s
separate depth and segmentation passes, so the GL context, MjrContext and MjvScene are driven directly here, with
`mujoco.Renderer`'s depth linearisation and segment-id decoding.
"""

from __future__ import annotations

import copy
import functools
import os
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from scipy.spatial import cKDTree

from partinstruct_mjx.errors import SceneError
from partinstruct_mjx.obs.cameras import AGENTVIEW, IMAGE_SIZE, WRIST, camera_pose, optical_to_world, scene_camera
from partinstruct_mjx.sim.scene import Scene
from partinstruct_mjx.sim.state import SceneState
from partinstruct_mjx.tasks.part_geometry import PartGeometry, PartNames, load_parts
from partinstruct_mjx.tasks.predicates import part_cloud

_CHEAP_FLAGS_OFF = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                    mujoco.mjtRndFlag.mjRND_SKYBOX)


@dataclass(frozen=True)
class CameraImages:
    """What one camera saw, and the poses it saw it from.

    Attributes:
      camera: camera name.
      rgb: (H, W, 3) uint8, or None when not rendered.
      depth: (H, W) float32 metres along the optical axis (the far-plane distance on background), or None.
      segmentation: (H, W) int32 geom ids, -1 on background, or None.
      intrinsics: (3, 3) pinhole K (pixel centres at integer + 0.5, as OpenGL rasterises).
      position, rotation: camera position (3,) and optical-frame rotation (3, 3) in the world (cameras.py).
      body_pos, body_quat: (nbody, 3), (nbody, 4) body poses of the rendered configuration.
    """

    camera: str
    rgb: np.ndarray | None
    depth: np.ndarray | None
    segmentation: np.ndarray | None
    intrinsics: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    body_pos: np.ndarray
    body_quat: np.ndarray

    @property
    def world_to_camera(self) -> np.ndarray:
        """(4, 4) world -> optical-frame transform (x right, y down, z forward)."""
        matrix = np.eye(4)
        matrix[:3, :3] = self.rotation.T
        matrix[:3, 3] = -self.rotation.T @ self.position
        return matrix


class _Poses(NamedTuple):
    """The two fields of a SceneState row that `predicates.part_cloud` reads."""

    body_pos: jnp.ndarray
    body_quat: jnp.ndarray


@jax.jit
def _part_points(body_pos, body_quat, geo: PartGeometry, masks, part):
    return part_cloud(_Poses(body_pos, body_quat), geo, masks, part)


class ImageRenderer:
    """Renders SceneState rows (either backend) from the 'agentview' or the hand-mounted 'wrist' camera.

    Holds one MjData and one GL context; not thread-safe. Use as a context manager or call `close()`.
    """

    def __init__(self, scene: Scene, width: int = IMAGE_SIZE, height: int = IMAGE_SIZE,
                 parts: tuple[PartGeometry, PartNames] | None = None):
        self.scene = scene
        self._parts = parts
        self.width, self.height = width, height
        model = copy.copy(scene.model)
        model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(width, model.vis.global_.offwidth)
        model.vis.global_.offheight = max(height, model.vis.global_.offheight)
        self.model = model
        self._data = mujoco.MjData(model)
        self.cameras = {name: scene_camera(scene, name, width, height) for name in (AGENTVIEW, WRIST)}
        self._camera_pose = {name: jax.jit(partial(camera_pose, cam)) for name, cam in self.cameras.items()}
        extent = model.stat.extent
        self._near, self._far = model.vis.map.znear * extent, model.vis.map.zfar * extent
        # Lookups indexed by segmentation id; the appended entry serves -1 (background).
        self._is_object = np.append(scene.geom_part >= 0, False)
        self._is_robot_or_object = np.append(model.geom_bodyid > 0, False)

        self._gl = _gl_context(width, height)
        self._gl.make_current()
        self._context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100.value)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN.value, self._context)
        self._context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        self._scene = mujoco.MjvScene(model, maxgeom=model.ngeom + 100)
        for flag in _CHEAP_FLAGS_OFF:
            self._scene.flags[flag] = False
        self._option = mujoco.MjvOption()
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._rgb = np.empty((height, width, 3), np.uint8)
        self._ids = np.empty((height, width, 3), np.uint8)
        self._zbuffer = np.empty((height, width), np.float32)

    @property
    def geometry(self) -> PartGeometry:
        """Part clouds of the object, loaded when a part mask first needs them (objects without parts.npz render)."""
        if self._parts is None:
            self._parts = load_parts(self.scene)
        return self._parts[0]

    @property
    def part_names(self) -> PartNames:
        """The labels of `geometry`'s rows."""
        self.geometry  # noqa: B018 (loads the parts)
        return self._parts[1]

    @functools.cached_property
    def _part_of_pixel(self) -> np.ndarray:
        return np.append(np.asarray(self.geometry.geom_part), -1).astype(np.int32)

    def close(self) -> None:
        """Free the GL resources."""
        if self._gl is not None:
            self._gl.make_current()
            self._context.free()
            self._gl.free()
            self._gl = None

    def __enter__(self) -> ImageRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(self, state: SceneState | np.ndarray, camera: str = AGENTVIEW, rgb: bool = True,
               depth_segmentation: bool = True) -> CameraImages:
        """Render one configuration: a SceneState row (its `qpos` is used) or a qpos vector (nq,).

        Args:
          state: what to show; poses are recomputed from qpos, so the wrist camera follows the hand.
          camera: 'agentview' or 'wrist'.
          rgb: render the colour image (one pass).
          depth_segmentation: render depth and segmentation (one more pass).
        """
        if camera not in self.cameras:
            raise SceneError(f"unknown camera '{camera}'; expected one of {', '.join(self.cameras)}")
        qpos = np.asarray(getattr(state, "qpos", state), dtype=float)
        if qpos.shape != (self.model.nq,):
            raise SceneError(f"render needs one scene's qpos of shape ({self.model.nq},), got {qpos.shape}")
        data = self._data
        data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_camlight(self.model, data)
        mjv_camera = mujoco.MjvCamera()
        mjv_camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        mjv_camera.fixedcamid = self.model.camera(camera).id
        mujoco.mjv_updateScene(self.model, data, self._option, None, mjv_camera, mujoco.mjtCatBit.mjCAT_ALL.value,
                               self._scene)
        self._gl.make_current()
        color = self._render_rgb() if rgb else None
        depth, segmentation = self._render_depth_segmentation() if depth_segmentation else (None, None)
        body_pos, body_quat = data.xpos.copy(), data.xquat.copy()
        position, rotation = (np.asarray(x) for x in self._camera_pose[camera](body_pos, body_quat))
        return CameraImages(camera, color, depth, segmentation, self.cameras[camera].intrinsics, position, rotation,
                            body_pos, body_quat)

    def _render_rgb(self) -> np.ndarray:
        mujoco.mjr_render(self._rect, self._scene, self._context)
        mujoco.mjr_readPixels(self._rgb, None, self._rect, self._context)
        return np.flipud(self._rgb).copy()

    def _render_depth_segmentation(self) -> tuple[np.ndarray, np.ndarray]:
        flags = self._scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        try:
            mujoco.mjr_render(self._rect, self._scene, self._context)
            mujoco.mjr_readPixels(self._ids, self._zbuffer, self._rect, self._context)
        finally:
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = False
        # Reversed-Z buffer (1 at near, 0 at far) -> metric depth, as mujoco.Renderer does it.
        near, far = self._near, self._far
        depth = (near * far / (np.flipud(self._zbuffer).astype(np.float64) * (far - near) + near)).astype(np.float32)
        ids = np.flipud(self._ids).astype(np.int32)
        segid = ids[..., 0] | (ids[..., 1] << 8) | (ids[..., 2] << 16)
        lookup = np.full(self._scene.ngeom + 1, -1, np.int32)
        for index in range(self._scene.ngeom):
            geom = self._scene.geoms[index]
            if geom.segid >= 0 and geom.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lookup[geom.segid + 1] = geom.objid
        return depth, lookup[segid]

    def robot_or_object(self, segmentation: np.ndarray) -> np.ndarray:
        """(H, W) bool: pixels of the robot or the object (not background, floor or table: world-body geoms)."""
        return self._is_robot_or_object[segmentation]

    def part_cloud(self, images: CameraImages, part: int, masks: jnp.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (M, 3) and validity (M,) of part row `part` in the rendered configuration."""
        points, valid = _part_points(images.body_pos, images.body_quat, self.geometry, jnp.asarray(masks), part)
        return np.asarray(points), np.asarray(valid)

    def part_mask(self, images: CameraImages, part: int | None, masks: jnp.ndarray) -> np.ndarray:
        """(H, W) uint8 0/1 mask of part row `part` as seen (occluded pixels are 0); all zeros for None.

        Semantic parts: pixels whose geom (visual or collision) carries the part's label. Spatial parts and the whole
        object (no geoms of their own): object pixels whose back-projected point's nearest whole-object surface
        point is in the part (`masks`: the env's (7, M) spatial masks). Nearest-point labelling instead of a
        distance threshold: surface samples lie up to ~5 mm apart, so a threshold would leave holes.
        """
        if part is None:
            return np.zeros((self.height, self.width), np.uint8)
        if images.segmentation is None or images.depth is None:
            raise SceneError("part_mask needs images rendered with depth_segmentation=True")
        segmentation = images.segmentation
        if part < self.geometry.num_semantic:
            return (self._part_of_pixel[segmentation] == part).astype(np.uint8)
        rows, cols = np.nonzero(self._is_object[segmentation])
        points = backproject(images.depth[rows, cols], rows, cols, images.intrinsics)
        world = np.asarray(optical_to_world(points, images.position, images.rotation))
        cloud, in_part = self.part_cloud(images, part, masks)
        mask = np.zeros(segmentation.shape, np.uint8)
        if len(rows):
            mask[rows, cols] = in_part[cKDTree(cloud).query(world)[1]]
        return mask


def _gl_context(width: int, height: int):
    """An offscreen GL context of MUJOCO_GL's backend; EGL when unset, since GLFW needs a display.

    Chosen here rather than by `import mujoco`, which fixes its default before this module can set MUJOCO_GL.
    """
    backend = (os.environ.get("MUJOCO_GL") or "egl").lower()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        GLContext = mujoco.GLContext
    return GLContext(width, height)


def backproject(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Optical-frame points (N, 3) of pixels (row, col) with metric depths (N,), through pixel centres."""
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    z = depth.astype(np.float64)
    return np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=-1)
