"""A contact sheet of objects with their parts coloured (docs/objects.png), rendered offscreen with MuJoCo."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
from PIL import Image, ImageDraw

from partinstruct_mjx.assets.naming import VISUAL_TAG, parse_geom_name

PART_COLOURS = np.array([
    [0.90, 0.30, 0.25], [0.20, 0.55, 0.90], [0.30, 0.75, 0.35], [0.95, 0.75, 0.20], [0.65, 0.40, 0.85],
    [0.20, 0.80, 0.80], [0.95, 0.50, 0.75], [0.55, 0.55, 0.55],
])
VIEW_DIRECTION = np.array([0.7, -0.5, 0.6])
"""From the object towards the camera: back-right and above (laptop keyboards and screens face +x)."""


def render_parts(object_xml: str | Path, size: int = 320) -> tuple[np.ndarray, list[str]]:
    """RGB image (size x size) of the object alone with each part in its own colour, and the part names."""
    spec = mujoco.MjSpec.from_file(str(object_xml))
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.55, 0.55, 0.55]
    spec.worldbody.add_light(pos=[0, 0, 2], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                             diffuse=[0.4, 0.4, 0.4])
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    parts: list[str] = []
    corners = []
    for g in range(model.ngeom):
        parsed = parse_geom_name(model.geom(g).name)
        if parsed is None or parsed[1] != VISUAL_TAG:
            continue
        if parsed[0] not in parts:
            parts.append(parsed[0])
        model.geom_rgba[g] = [*PART_COLOURS[parts.index(parsed[0]) % len(PART_COLOURS)], 1.0]
        model.geom_matid[g] = -1
        rot = data.geom_xmat[g].reshape(3, 3)
        centre, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        box = np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * half + centre
        corners.append(box @ rot.T + data.geom_xpos[g])
    corners = np.concatenate(corners)
    centre = (corners.max(axis=0) + corners.min(axis=0)) / 2
    radius = np.linalg.norm(corners - centre, axis=1).max()
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = centre
    direction = VIEW_DIRECTION / np.linalg.norm(VIEW_DIRECTION)
    camera.azimuth = np.degrees(np.arctan2(direction[1], direction[0]))
    camera.elevation = -np.degrees(np.arcsin(direction[2]))
    camera.distance = 1.15 * radius / np.sin(np.radians(model.vis.global_.fovy / 2))
    with mujoco.Renderer(model, size, size) as renderer:
        renderer.update_scene(data, camera)
        return renderer.render().copy(), parts


def contact_sheet(tiles: list[tuple[str, str | Path]], columns: int = 5, size: int = 300) -> Image.Image:
    """A grid of (title, object.xml) renders, each with its title and a colour legend of its parts."""
    legend_height = 18 * (1 + len(PART_COLOURS) // 2) + 4
    rows = -(-len(tiles) // columns)
    sheet = Image.new("RGB", (columns * size, rows * (size + legend_height)), "white")
    draw = ImageDraw.Draw(sheet)
    for index, (title, xml) in enumerate(tiles):
        image, parts = render_parts(xml, size)
        x, y = (index % columns) * size, (index // columns) * (size + legend_height)
        sheet.paste(Image.fromarray(image), (x, y))
        draw.text((x + 6, y + 4), title, fill="white")
        for k, part in enumerate(parts):
            lx, ly = x + 6 + (k % 2) * (size // 2), y + size + 4 + 18 * (k // 2)
            colour = tuple(int(255 * c) for c in PART_COLOURS[k % len(PART_COLOURS)])
            draw.rectangle([lx, ly + 2, lx + 10, ly + 12], fill=colour)
            draw.text((lx + 14, ly), part, fill="black")
    return sheet
