"""Scene assembly with MjSpec: the Panda at its base pose, a table, one part-labelled object, cameras, lights.

The collision set follows DESIGN.md: the table top is a plane, the object collides with the table and the
gripper only, arm links with the table only, and no two parts of the object collide with each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from partinstruct_mjx import paths
from partinstruct_mjx.assets.naming import COLLISION_TAG, parse_geom_name
from partinstruct_mjx.errors import AssetError, SceneError
from partinstruct_mjx.sim import panda

TABLE_HEIGHT = 0.06
"""Height of the table top (spec 1.2: 'a horizontal surface at roughly z = 0.06')."""

OBJECT_X_RANGE = (-0.05, 0.08)
OBJECT_Y_RANGE = (-0.085, 0.2)
"""Where objects are placed on the table (the original's workspace helper, spec 1.4)."""

OBJECT_PREFIX = "object/"
OBJECT_ROOT_JOINT = OBJECT_PREFIX + "root"

# contype/conaffinity bits; see assets_mjcf/robots/panda/panda.xml for the robot's side.
TABLE_BITS = (1, 0)
OBJECT_BITS = (2, 1)

# Static "agentview" camera of the original (spec 1.5), as a MuJoCo camera.
AGENTVIEW_POS = (-1.00175, 0.05, 0.77362)
AGENTVIEW_XYAXES = (0.0, -1.0, 0.0, 0.34202, 0.0, 0.93969)
AGENTVIEW_FOVY = 60.0


@dataclass(frozen=True)
class SceneConfig:
    """What goes into a scene and how it is simulated.

    Attributes:
      object_xml: object MJCF (converter layout); None selects the built-in default object.
      timestep: physics step in seconds.
      substeps: physics steps per control step (0.005 s x 10 = the original's 20 Hz control rate).
      solver_iterations: Newton solver iterations per physics step.
      linesearch_iterations: line-search iterations per Newton iteration.
      noslip_iterations: iterations of MuJoCo's no-slip pass after the solver (C backend only; MJX ignores it).
        Soft contacts let a held object creep through the pads under a steady load (a bottle held across its middle
        pivoted 38 degrees in 4 s); the pass makes friction hard, and with the pads' torsional friction grasps hold.
      settle_steps: control steps the object settles for at reset (spec 1.4b: 60 steps = 3 s).
      contact_split: while a finger pad touches anything, the C backend splits each physics step into this many
        (1: never). The 35 N pinch of a stiff pad contact on a 2 mm scissors blade or a tapered cap chattered at 5 ms
        steps (contacts lost and found from one step to the next) until the pads tunnelled or the object slipped
        out; split in two, 708 instead of 678 of 880 oracle episodes succeeded (docs/oracle.md). MJX steps at
        `timestep` throughout.
    """

    object_xml: str | None = None
    timestep: float = 0.005
    substeps: int = 10
    solver_iterations: int = 20
    linesearch_iterations: int = 10
    noslip_iterations: int = 10
    settle_steps: int = 60
    contact_split: int = 2

    def __post_init__(self):
        if self.contact_split < 1:
            raise SceneError(f"contact_split must be >= 1, got {self.contact_split}")

    @property
    def control_dt(self) -> float:
        """Seconds per control (environment) step."""
        return self.timestep * self.substeps


@dataclass(frozen=True)
class Scene:
    """A compiled scene and the indices that the backends and predicates need."""

    model: mujoco.MjModel
    config: SceneConfig
    object_xml: Path
    arm_qpos_adr: np.ndarray
    arm_dof_adr: np.ndarray
    finger_qpos_adr: np.ndarray
    object_qpos_adr: int
    object_dof_adr: int
    object_body: int
    object_bodies: np.ndarray
    hand_body: int
    tcp_site: int
    table_geom: int
    geom_finger: np.ndarray = field(repr=False)
    """Per geom: 0 for the left finger, 1 for the right finger, -1 otherwise."""
    geom_part: np.ndarray = field(repr=False)
    """Per geom: index into `part_names` for object geoms, -1 otherwise."""
    part_names: tuple[str, ...] = ()

    @property
    def object_geoms(self) -> np.ndarray:
        """Ids of the object's collision geoms."""
        return np.flatnonzero((self.geom_part >= 0) & (self.model.geom_contype > 0))


def build_scene(config: SceneConfig = SceneConfig()) -> Scene:
    """Assemble and compile the scene for `config`; raises AssetError naming a missing or broken file."""
    object_xml = Path(config.object_xml) if config.object_xml else paths.default_object_xml()
    spec = _load_spec(paths.robot_xml())
    spec.modelname = "partinstruct_scene"
    _set_options(spec, config)
    spec.body("panda_link0").pos = panda.BASE_POS
    _add_environment(spec)
    _add_object(spec, object_xml)
    try:
        model = spec.compile()
    except ValueError as err:
        raise AssetError(f"cannot compile the scene with object {object_xml}: {err}") from err
    return _index_scene(model, config, object_xml)


def _load_spec(path: Path) -> mujoco.MjSpec:
    if not path.is_file():
        raise AssetError(f"MJCF file not found: {path}")
    try:
        return mujoco.MjSpec.from_file(str(path))
    except ValueError as err:
        raise AssetError(f"cannot parse MJCF {path}: {err}") from err


def _set_options(spec: mujoco.MjSpec, config: SceneConfig) -> None:
    opt = spec.option
    opt.timestep = config.timestep
    opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    opt.iterations = config.solver_iterations
    opt.ls_iterations = config.linesearch_iterations
    opt.noslip_iterations = config.noslip_iterations
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480


def _add_environment(spec: mujoco.MjSpec) -> None:
    """Floor, table (a collision plane plus a visual slab), the agentview camera and lights."""
    spec.add_texture(name="floor_tex", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.32, 0.34, 0.36], rgb2=[0.26, 0.28, 0.30], width=256, height=256)
    spec.add_material(name="floor_mat", textures=["", "floor_tex"], texrepeat=[6, 6], reflectance=0.0)
    spec.add_material(name="table_mat", rgba=[0.62, 0.50, 0.38, 1.0])
    world = spec.worldbody
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.05], material="floor_mat",
                   contype=0, conaffinity=0, group=2)
    world.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], pos=[0, 0, TABLE_HEIGHT],
                   contype=TABLE_BITS[0], conaffinity=TABLE_BITS[1], condim=3, friction=[0.5, 0.005, 0.0001],
                   rgba=[0, 0, 0, 0], group=3)
    world.add_geom(name="table_top", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.55, 0.7, TABLE_HEIGHT / 2],
                   pos=[0.15, 0.05, TABLE_HEIGHT / 2], material="table_mat", contype=0, conaffinity=0, group=2)
    camera = world.add_camera(name="agentview", pos=AGENTVIEW_POS, fovy=AGENTVIEW_FOVY)
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = AGENTVIEW_XYAXES
    world.add_light(name="key", pos=[0.0, -0.4, 2.0], dir=[0.0, 0.2, -1.0], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                    diffuse=[0.7, 0.7, 0.7], specular=[0.1, 0.1, 0.1], castshadow=False)
    world.add_light(name="fill", pos=[-1.0, 0.5, 1.5], dir=[0.6, -0.3, -0.7], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                    diffuse=[0.35, 0.35, 0.35], specular=[0.0, 0.0, 0.0], castshadow=False)


def _add_object(spec: mujoco.MjSpec, object_xml: Path) -> None:
    """Attach the object's root body under a free joint and enforce the object's collision bits."""
    object_spec = _load_spec(object_xml)
    roots = list(object_spec.worldbody.bodies)
    if len(roots) != 1:
        raise AssetError(f"{object_xml}: expected exactly one root body in <worldbody>, found {len(roots)}")
    root_name = OBJECT_PREFIX + roots[0].name
    frame = spec.worldbody.add_frame(pos=[0.0, 0.0, 0.5])
    spec.attach(object_spec, frame=frame, prefix=OBJECT_PREFIX)
    root = spec.body(root_name)
    root.add_freejoint(name=OBJECT_ROOT_JOINT)
    collision_geoms = 0
    for body in [root, *root.find_all(mujoco.mjtObj.mjOBJ_BODY)]:
        for geom in body.geoms:
            if geom.contype or geom.conaffinity:
                geom.contype, geom.conaffinity = OBJECT_BITS
                collision_geoms += 1
    if collision_geoms == 0:
        raise AssetError(f"{object_xml}: the object has no collision geoms")


def _index_scene(model: mujoco.MjModel, config: SceneConfig, object_xml: Path) -> Scene:
    def joint(name):
        return model.joint(name)

    object_joint = joint(OBJECT_ROOT_JOINT)
    object_body = int(object_joint.bodyid[0])
    object_bodies = np.array([b for b in range(model.nbody) if _has_ancestor(model, b, object_body)])
    geom_finger = np.full(model.ngeom, -1, dtype=np.int32)
    for index, body_name in enumerate(panda.FINGER_BODIES):
        geom_finger[model.geom_bodyid == model.body(body_name).id] = index
    part_names: list[str] = []
    geom_part = np.full(model.ngeom, -1, dtype=np.int32)
    for geom_id in range(model.ngeom):
        if model.geom_bodyid[geom_id] not in object_bodies:
            continue
        parsed = parse_geom_name(model.geom(geom_id).name)
        if parsed is None:
            raise AssetError(f"{object_xml}: geom '{model.geom(geom_id).name}' is not named '<part>/col<k>' "
                             f"or '<part>/vis<k>'")
        label, kind = parsed
        if label not in part_names:
            part_names.append(label)
        geom_part[geom_id] = part_names.index(label)
        if kind != COLLISION_TAG and model.geom_contype[geom_id]:
            raise AssetError(f"{object_xml}: visual geom '{model.geom(geom_id).name}' must not collide")
    return Scene(
        model=model,
        config=config,
        object_xml=object_xml,
        arm_qpos_adr=np.array([joint(n).qposadr[0] for n in panda.ARM_JOINTS]),
        arm_dof_adr=np.array([joint(n).dofadr[0] for n in panda.ARM_JOINTS]),
        finger_qpos_adr=np.array([joint(n).qposadr[0] for n in panda.FINGER_JOINTS]),
        object_qpos_adr=int(object_joint.qposadr[0]),
        object_dof_adr=int(object_joint.dofadr[0]),
        object_body=object_body,
        object_bodies=object_bodies,
        hand_body=model.body(panda.HAND_BODY).id,
        tcp_site=model.site(panda.TCP_SITE).id,
        table_geom=model.geom("table").id,
        geom_finger=geom_finger,
        geom_part=geom_part,
        part_names=tuple(part_names),
    )


def _has_ancestor(model: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body != 0:
        if body == ancestor:
            return True
        body = model.body_parentid[body]
    return False


def random_placements(batch: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(B, 2) object x/y in the workspace and (B, 4) random-yaw orientations (w, x, y, z), from `seed`."""
    rng = np.random.default_rng(seed)
    xy = np.column_stack([rng.uniform(*OBJECT_X_RANGE, batch), rng.uniform(*OBJECT_Y_RANGE, batch)])
    yaw = rng.uniform(-np.pi, np.pi, batch)
    return xy, np.column_stack([np.cos(yaw / 2), np.zeros(batch), np.zeros(batch), np.sin(yaw / 2)])
