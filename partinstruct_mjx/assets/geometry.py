"""Assembling a PartNet object into bodies, per-part collision meshes and per-material visual meshes.

Fixed joints are merged into their parent body (all joints with `rigid=True`); every moving link becomes a body
with its joint. Everything is expressed in body frames, in metres, after the object scale.
"""

from __future__ import annotations

import hashlib
import io
import warnings
from dataclasses import dataclass, field

import numpy as np
import PIL.Image
import trimesh
from scipy.spatial.transform import Rotation

from partinstruct_mjx.assets.partnet import Joint, PartNetObject, Visual
from partinstruct_mjx.errors import AssetError


@dataclass(frozen=True)
class JointSpec:
    name: str
    kind: str
    """'hinge' or 'slide'."""
    axis: np.ndarray
    range: tuple[float, float] | None


@dataclass
class BodySpec:
    name: str
    parent: str | None
    transform: np.ndarray
    """Body frame in the parent body frame (4x4, scaled)."""
    joint: JointSpec | None = None


@dataclass
class Material:
    rgba: np.ndarray
    texture_png: bytes | None = None


@dataclass
class MeshPiece:
    body: str
    part: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    material: str = ""
    source_sizes: tuple[tuple[int, int], ...] = ()
    """(vertices, faces) of each source mesh (OBJ file) concatenated into this piece, in order."""

    def sources(self) -> list[MeshPiece]:
        """The piece's source meshes as pieces of their own, in order (concatenated, they give this piece back)."""
        pieces, vertex_start, face_start = [], 0, 0
        for vertex_count, face_count in self.source_sizes:
            faces = self.faces[face_start:face_start + face_count] - vertex_start
            pieces.append(MeshPiece(self.body, self.part, self.vertices[vertex_start:vertex_start + vertex_count],
                                    faces, material=self.material, source_sizes=((vertex_count, face_count),)))
            vertex_start, face_start = vertex_start + vertex_count, face_start + face_count
        return pieces


@dataclass
class AssembledObject:
    bodies: list[BodySpec]
    collision: list[MeshPiece]
    """One mesh per (body, part): the part's geometry to decompose and sample (the converter may split a part into
    its source meshes, `decompose.separate_sources`)."""
    visual: list[MeshPiece]
    """One mesh per (body, part, material)."""
    materials: dict[str, Material] = field(default_factory=dict)
    scale: float = 1.0


def assemble(obj: PartNetObject, scale: float | None, target_size: float | None, rigid: bool) -> AssembledObject:
    """Bodies and meshes of `obj`; the scale is `scale`, or chosen so the largest extent equals `target_size`."""
    bodies, pieces = _flatten(obj, rigid)
    loaded = [(body, transform, visual, _load_obj(visual)) for body, transform, visual in pieces]
    mtl_cache: dict = {}
    if scale is None:
        if target_size is None:
            raise AssetError("give a scale or a target size")
        scale = target_size / _extent(bodies, loaded)
    for body in bodies:
        body.transform[:3, 3] *= scale
        if body.joint and body.joint.kind == "slide" and body.joint.range:
            body.joint = JointSpec(body.joint.name, "slide", body.joint.axis,
                                   (body.joint.range[0] * scale, body.joint.range[1] * scale))
    materials: dict[str, Material] = {}
    collision: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
    source_sizes: dict[tuple[str, str], list[tuple[int, int]]] = {}
    visual: dict[tuple[str, str, str], list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]] = {}
    for body, transform, source, meshes in loaded:
        part = obj.mesh_labels[source.stem]
        if meshes:
            source_sizes.setdefault((body, part), []).append(
                (sum(len(m.vertices) for m in meshes), sum(len(m.faces) for m in meshes)))
        for mesh in meshes:
            vertices = _apply(transform, mesh.vertices * source.scale) * scale
            collision.setdefault((body, part), []).append((vertices, mesh.faces))
            key = _material_key(mesh, _read_mtl(source.mesh, mtl_cache), materials, mtl_cache)
            uv = getattr(mesh.visual, "uv", None) if materials[key].texture_png else None
            visual.setdefault((body, part, key), []).append((vertices, mesh.faces, uv))
    return AssembledObject(
        bodies=bodies,
        collision=[MeshPiece(b, p, *_concatenate(items)[:2], source_sizes=tuple(source_sizes[(b, p)]))
                   for (b, p), items in collision.items()],
        visual=[MeshPiece(b, p, *_concatenate(items), material=m) for (b, p, m), items in visual.items()],
        materials=materials,
        scale=float(scale),
    )


def _flatten(obj: PartNetObject, rigid: bool) -> tuple[list[BodySpec], list[tuple[str, np.ndarray, Visual]]]:
    """Bodies, and every visual with its body and its pose in that body's frame."""
    children: dict[str, list[Joint]] = {}
    for joint in obj.joints:
        children.setdefault(joint.parent, []).append(joint)
    bodies = [BodySpec(obj.root_link, None, np.eye(4))]
    pieces = []

    def visit(link: str, body: str, link_in_body: np.ndarray):
        for visual in obj.links[link]:
            pieces.append((body, link_in_body @ visual.transform, visual))
        for joint in children.get(link, []):
            if rigid or joint.type == "fixed" or (joint.limits and joint.limits[0] == joint.limits[1]):
                visit(joint.child, body, link_in_body @ joint.transform)
                continue
            kind = "slide" if joint.type == "prismatic" else "hinge"
            bodies.append(BodySpec(joint.child, body, link_in_body @ joint.transform,
                                   JointSpec(joint.name, kind, joint.axis, joint.limits)))
            visit(joint.child, joint.child, np.eye(4))

    visit(obj.root_link, obj.root_link, np.eye(4))
    return bodies, pieces


def _load_obj(visual: Visual) -> list[trimesh.Trimesh]:
    try:
        with warnings.catch_warnings():  # trimesh warns about UV-less pieces of textured files; they are fine
            warnings.simplefilter("ignore", RuntimeWarning)
            loaded = trimesh.load(visual.mesh, process=False, maintain_order=True)
    except Exception as err:  # trimesh raises many types for unreadable files
        raise AssetError(f"cannot read mesh {visual.mesh}: {err}") from err
    meshes = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
    meshes = [m for m in meshes if isinstance(m, trimesh.Trimesh) and len(m.faces)]
    if not meshes:
        raise AssetError(f"empty mesh (no faces): {visual.mesh}")
    return meshes


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _world_transforms(bodies: list[BodySpec]) -> dict[str, np.ndarray]:
    world = {}
    for body in bodies:  # parents come before children
        world[body.name] = body.transform if body.parent is None else world[body.parent] @ body.transform
    return world


def _extent(bodies, loaded) -> float:
    world = _world_transforms(bodies)
    points = np.concatenate([_apply(world[b] @ t, m.vertices * v.scale) for b, t, v, meshes in loaded for m in meshes])
    extent = float((points.max(axis=0) - points.min(axis=0)).max())
    if extent <= 0:
        raise AssetError("the object's meshes have zero extent")
    return extent


def _read_mtl(obj_path, cache: dict) -> dict[str, tuple[np.ndarray, object]]:
    """Material name -> (diffuse rgb, texture path or None) from the OBJ's mtllib files (paths relative to them).

    trimesh does not resolve the dataset's `map_Kd ../images/...` paths, so the MTL files are read here.
    """
    if obj_path in cache:
        return cache[obj_path]
    materials: dict[str, tuple[np.ndarray, object]] = {}
    for line in obj_path.read_text(errors="replace").splitlines():
        if not line.startswith("mtllib"):
            continue
        mtl = obj_path.parent / line.split(maxsplit=1)[1].strip()
        if not mtl.is_file():
            raise AssetError(f"{obj_path}: material library not found: {mtl}")
        name = None
        for entry in mtl.read_text(errors="replace").splitlines():
            fields = entry.split()
            if not fields:
                continue
            if fields[0] == "newmtl":
                name = entry.split(maxsplit=1)[1].strip()
                materials[name] = (np.array([0.8, 0.8, 0.8]), None)
            elif name and fields[0] == "Kd" and len(fields) >= 4:
                try:
                    materials[name] = (np.array([float(v) for v in fields[1:4]]), materials[name][1])
                except ValueError:
                    raise AssetError(f"{mtl}: material '{name}' has a malformed Kd line: '{entry}'") from None
            elif name and fields[0] == "map_Kd":
                texture = (mtl.parent / fields[-1]).resolve()
                materials[name] = (materials[name][0], texture if texture.is_file() else None)
    cache[obj_path] = materials
    return materials


def _material_key(mesh: trimesh.Trimesh, library: dict, materials: dict[str, Material], cache: dict) -> str:
    """Register the mesh's material (a texture if it has one and UVs, else its diffuse colour); return its key."""
    name = getattr(getattr(mesh.visual, "material", None), "name", None)
    rgb, texture = library.get(name, (np.array([0.8, 0.8, 0.8]), None))
    uv = getattr(mesh.visual, "uv", None)
    png = None
    if texture is not None and uv is not None and len(uv) == len(mesh.vertices):
        if texture not in cache:
            try:
                buffer = io.BytesIO()
                PIL.Image.open(texture).convert("RGB").save(buffer, format="PNG")
            except OSError as err:
                raise AssetError(f"cannot read texture {texture}: {err}") from err
            cache[texture] = buffer.getvalue()
        png = cache[texture]
    rgba = np.ones(4) if png else np.append(np.clip(rgb, 0.0, 1.0), 1.0)
    digest = hashlib.sha1(png if png else np.round(rgba, 3).tobytes()).hexdigest()[:10]
    key = f"{'tex' if png else 'rgb'}_{digest}"
    materials.setdefault(key, Material(rgba=rgba, texture_png=png))
    return key


def _concatenate(items):
    offsets = np.cumsum([0] + [len(v) for v, *_ in items])[:-1]
    vertices = np.concatenate([v for v, *_ in items])
    faces = np.concatenate([f + o for (_, f, *_), o in zip(items, offsets)])
    uvs = [rest[0] if rest else None for _, _, *rest in items]
    uv = np.concatenate(uvs) if all(u is not None for u in uvs) and uvs and len(items[0]) == 3 else None
    return vertices, faces, uv


def quat_wxyz(transform: np.ndarray) -> np.ndarray:
    """Rotation part of a 4x4 transform as a (w, x, y, z) quaternion."""
    return np.roll(Rotation.from_matrix(transform[:3, :3]).as_quat(), 1)
