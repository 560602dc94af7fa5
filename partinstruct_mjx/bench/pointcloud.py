"""Scene point clouds per second: the JAX point renderer on the current JAX device, and the OpenGL path on a CPU.

The OpenGL path is the original's pipeline (`obs/depth_cloud.py`): depth and segmentation images of the agentview
camera, table/floor/background pixels dropped, the rest back-projected and farthest-point sampled to 1024 points.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from partinstruct_mjx.bench.timing import Throughput, measure_throughput
from partinstruct_mjx.obs import point_renderer
from partinstruct_mjx.obs.cameras import AGENTVIEW, Camera, scene_camera
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import Scene
from partinstruct_mjx.sim.state import SceneState
from partinstruct_mjx.tasks.part_geometry import PartGeometry, PartNames, load_parts


@dataclass(frozen=True)
class JaxResult:
    sampler: str
    batch_size: int
    timing: Throughput
    """Clouds per second."""


@dataclass(frozen=True)
class GLResult:
    clouds: int
    render_per_s: float
    """Depth + segmentation images per second (one scene after another, median)."""
    clouds_per_s: float
    """Clouds per second of the whole path: render, back-project, farthest-point sample 1024 points (median)."""


@dataclass(frozen=True)
class PointCloudBenchResults:
    device: str
    object_name: str
    surface_points: int
    speed: list[JaxResult]
    gl: GLResult | None
    gl_error: str = ""
    """Why the OpenGL path was not measured (no OpenGL context, e.g. MUJOCO_GL unset on a headless machine)."""


def measure(scene: Scene, batch_sizes: tuple[int, ...] = (1, 16, 256), repeats: int = 5,
            samplers: tuple[str, ...] = point_renderer.SAMPLERS, min_clouds: int = 256, gl_clouds: int = 100,
            seed: int = 0) -> PointCloudBenchResults:
    """Clouds/s of `render_batch` per sampler and batch size (each repeat renders >= `min_clouds` clouds), and of the
    OpenGL path for `gl_clouds` scenes. The scene's object needs a parts.npz (the built-in test block has none); the
    scene is reset once and its settled poses are rendered. On a GPU, batches of 1,024-16,384 saturate an H100."""
    geometry, names = load_parts(scene)
    surface = point_renderer.surface_points(scene, geometry, seed=seed)
    camera = scene_camera(scene, AGENTVIEW)
    with MujocoBackend(scene, 1) as backend:
        state = backend.reset()
    gl, gl_error = _measure_gl(scene, (geometry, names), jax.tree_util.tree_map(lambda x: x[0], state), gl_clouds)
    speed = [_measure_jax(surface, camera, state, size, sampler, repeats, min_clouds, seed)
             for sampler in samplers for size in batch_sizes]
    device = jax.devices()[0]
    name = "CPU" if device.platform == "cpu" else device.device_kind
    return PointCloudBenchResults(name, scene.object_xml.parent.name, int(surface.points.shape[0]), speed, gl,
                                  gl_error)


def _measure_jax(surface: point_renderer.SurfacePoints, camera: Camera, state: SceneState, batch_size: int,
                 sampler: str, repeats: int, min_clouds: int, seed: int) -> JaxResult:
    def tile(x):
        return jax.device_put(jnp.tile(jnp.asarray(x[:1]), (batch_size,) + (1,) * (x.ndim - 1)))

    args = (tile(state.body_pos), tile(state.body_quat), jnp.zeros((batch_size, surface.num_object), bool),
            jax.random.split(jax.random.PRNGKey(seed), batch_size))

    timing = measure_throughput(lambda: point_renderer.render_batch(surface, camera, *args, sampler=sampler).points,
                                batch_size, repeats, min_clouds)
    return JaxResult(sampler, batch_size, timing)


def _measure_gl(scene: Scene, parts: tuple[PartGeometry, PartNames], state_row: SceneState,
                clouds: int) -> tuple[GLResult | None, str]:
    """Time the OpenGL observation path (`obs/images.py`, `obs/depth_cloud.py`) on one settled scene; (None, reason)
    where no OpenGL context can be made."""
    from partinstruct_mjx.obs.depth_cloud import scene_cloud
    from partinstruct_mjx.obs.images import ImageRenderer

    try:
        renderer = ImageRenderer(scene, parts=parts)
    except Exception as err:  # noqa: BLE001 - any GL failure (no EGL, no display) means "not measured"
        return None, f"{type(err).__name__}: {err}".splitlines()[0]
    with renderer:
        times = np.zeros((clouds, 2))
        for i in range(clouds):
            start = time.perf_counter()
            images = renderer.render(state_row, AGENTVIEW, rgb=False)
            rendered = time.perf_counter()
            scene_cloud(renderer, images)
            times[i] = rendered - start, time.perf_counter() - rendered
    render, cloud = np.median(times, axis=0)
    return GLResult(clouds, 1 / render, 1 / (render + cloud)), ""


def markdown(results: PointCloudBenchResults) -> str:
    """A table of JAX clouds/s per sampler and batch size, and a line for the OpenGL path."""
    rows = "\n".join(
        f"| {r.sampler} | {r.batch_size:,} | {r.timing.cells()} |" for r in results.speed)
    if results.gl is None:
        gl = f"OpenGL path not measured ({results.gl_error}).\n"
    else:
        g = results.gl
        gl = (f"OpenGL path (`obs/images.py` + `obs/depth_cloud.py`: one depth + segmentation pass, "
              f"back-projection of the robot and object pixels, NumPy farthest-point sampling to "
              f"{point_renderer.PCD_SIZE} points; one scene after another, median of {g.clouds}): "
              f"{g.render_per_s:,.0f} images/s rendered, {g.clouds_per_s:,.0f} clouds/s.\n")
    return (
        f"JAX point renderer (`partinstruct_mjx/obs/point_renderer.py`) on {results.device}: Panda + "
        f"`{results.object_name}`, agentview camera, {results.surface_points:,} surface points (robot, object, table) "
        f"z-buffered on a {point_renderer.ZBUFFER_CELL} px grid, {point_renderer.PCD_SIZE} points per cloud. 'fps' = "
        f"farthest-point sampling over {point_renderer.FPS_CANDIDATES} x {point_renderer.PCD_SIZE} evenly drawn "
        f"visible points, 'stride' = evenly spaced visible points from a random offset.\n\n"
        "| sampler | batch | clouds/s (median) | range over repeats | compile s |\n|---|---|---|---|---|\n"
        + rows + "\n\n" + gl)
