"""The PyBullet side of the CPU benchmark: one env step done the original's way (spec 1.1-1.6, 4).

`PyBulletScene` builds, in a DIRECT client, a table plane at z = 0.06, the Panda from pybullet_data at the original's
base pose and home joints with the original's motor settings and finger gear constraint, and one object made of the
SAME convex hulls our converter wrote (`meshes/col_*.stl`), merged into one rigid object in the rest pose (the base
is the first hull; every further hull is a fixed-joint link, like the original's PartNet URDFs), 0.2 kg in all,
placed as our env places it (lowest point 5 mm above the table, then settled).

`step_like_the_original(tcp_pos, tcp_quat_xyzw, finger)` is one env step: `calculateInverseKinematics` on link 11
(20 iterations, seeded from the current state, no joint limits: spec 1.6 / 12 #2), position motors (arm force 2400,
gain 0.01; fingers force 5000, gain 0.01), 12 x `stepSimulation` at 240 Hz, then the predicates on 10,000-point NumPy
clouds: the object and target-part clouds transformed by the base pose, ON (getClosestPoints, 1 mm), GRIPPER_OPEN,
MIN_DISTANCE, GRASPING (contact forces > 20 N and a brute-force NumPy nearest-point search of the finger contact
positions against the part cloud, 3 mm), FACING (cloud mean vs base position) and TOUCHING's distance part (fingertip
to part cloud, 1 cm). TOUCHING's extra `world.step()` (12 more physics steps per evaluation in the original, spec
12 #3) is NOT done here, so the figure is generous to PyBullet.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from partinstruct_mjx.sim import panda
from partinstruct_mjx.sim.mujoco_backend import DROP_CLEARANCE, initial_positions
from partinstruct_mjx.sim.scene import OBJECT_PREFIX, TABLE_HEIGHT, SceneConfig, build_scene

TIMESTEP = 1.0 / 240.0
SUBSTEPS = 12
SOLVER_ITERATIONS = 150
ARM_FORCE, FINGER_FORCE, KP = 2400.0, 5000.0, 0.01
EE_LINK, LEFT_FINGER, RIGHT_FINGER = 11, 9, 10
ARM_JOINTS = tuple(range(7))
TCP_OFFSET = 0.05  # TCP = link 11 translated -0.05 along its z (spec 1.3)
FINGERTIP_OFFSET = 0.05 + 0.05 / 8
OBJECT_MASS = 0.2
CLOUD_POINTS = 10_000
HOME_TCP_POS = np.array([0.5748, 0.5751, 0.3478])
HOME_TCP_QUAT_XYZW = np.array([0.2656, 0.9591, -0.0876, -0.0446])


@dataclass(frozen=True)
class PyBulletResult:
    env_steps_per_s: float
    """Median over repeats (one process, one core)."""
    spread: tuple[float, float]
    """Slowest and fastest repeat, env steps/s."""


def _resample(points: np.ndarray, n: int, rng: np.random.Generator, jitter: float = 1e-3) -> np.ndarray:
    idx = rng.integers(0, len(points), n)
    return points[idx] + rng.normal(0.0, jitter, (n, 3))


def _quat_wxyz_to_mat(q) -> np.ndarray:
    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(q, float))
    return m.reshape(3, 3)


class PyBulletScene:
    """Table + pybullet_data Panda + one converted object in a DIRECT PyBullet client (see the module docstring)."""

    def __init__(self, object_xml: str | Path, part: str | None = None, object_xy=(0.0, -0.03),
                 settle_steps: int = 60, seed: int = 0):
        import pybullet as p
        import pybullet_data

        self.p = p
        self.object_xml = Path(object_xml)
        self.rng = np.random.default_rng(seed)
        cid = self.client = p.connect(p.DIRECT)
        p.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
        p.setPhysicsEngineParameter(fixedTimeStep=TIMESTEP, numSolverIterations=SOLVER_ITERATIONS,
                                    solverResidualThreshold=0, physicsClientId=cid)
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
        self.table = p.createMultiBody(0, plane, basePosition=[0, 0, TABLE_HEIGHT], physicsClientId=cid)
        self.robot = p.loadURDF("franka_panda/panda.urdf", basePosition=panda.BASE_POS.tolist(),
                                baseOrientation=[0, 0, 0, 1], useFixedBase=True, physicsClientId=cid,
                                flags=p.URDF_USE_SELF_COLLISION | p.URDF_ENABLE_CACHED_GRAPHICS_SHAPES)
        self.reset_robot()
        gear = p.createConstraint(self.robot, LEFT_FINGER, self.robot, RIGHT_FINGER, p.JOINT_GEAR, [1, 0, 0],
                                  [0, 0, 0], [0, 0, 0], physicsClientId=cid)
        p.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=50, physicsClientId=cid)
        for link in range(-1, p.getNumJoints(self.robot, physicsClientId=cid)):
            p.changeDynamics(self.robot, link, linearDamping=0, angularDamping=0, physicsClientId=cid)
        p.setCollisionFilterPair(self.robot, self.robot, LEFT_FINGER, RIGHT_FINGER, 0, physicsClientId=cid)
        self._build_object(part)
        for _ in range(settle_steps):
            self.step_physics(HOME_TCP_POS, HOME_TCP_QUAT_XYZW, panda.FINGER_OPEN, ik=False)

    # ----------------------------------------------------------------------------------------------------- building
    def reset_robot(self) -> None:
        """Hard-set the home joints (arm + open fingers) with zero velocity and home motor targets."""
        p, cid = self.p, self.client
        for j, q in zip(ARM_JOINTS, panda.HOME_ARM_QPOS):
            p.resetJointState(self.robot, j, q, 0.0, physicsClientId=cid)
        for j in (LEFT_FINGER, RIGHT_FINGER):
            p.resetJointState(self.robot, j, panda.FINGER_OPEN, 0.0, physicsClientId=cid)
        self._set_motors(panda.HOME_ARM_QPOS, panda.FINGER_OPEN)

    def _build_object(self, part: str | None) -> None:
        """The converter's hulls in the object's rest pose (poses from MuJoCo), one rigid multibody, COM frame."""
        import trimesh

        p, cid = self.p, self.client
        scene = build_scene(SceneConfig(object_xml=str(self.object_xml)))
        model, data = scene.model, mujoco.MjData(scene.model)
        qpos, _ = initial_positions(scene, 1)
        data.qpos[:] = qpos[0]
        mujoco.mj_kinematics(model, data)
        spec = mujoco.MjSpec.from_file(str(self.object_xml))
        mesh_files = {m.name: m.file for m in spec.meshes}
        meshdir = self.object_xml.parent / (spec.meshdir or "")

        def body_pose(name):  # world pose of an object body in the rest configuration
            b = model.body(OBJECT_PREFIX + name).id
            return data.xpos[b].copy(), data.xmat[b].reshape(3, 3).copy()

        hulls, weights = [], []
        for body in spec.worldbody.find_all(mujoco.mjtObj.mjOBJ_BODY):
            if not body.geoms:
                continue
            pos, rot = body_pose(body.name)
            for geom in body.geoms:
                if geom.type != mujoco.mjtGeom.mjGEOM_MESH or not (geom.contype or geom.conaffinity):
                    continue
                mesh = trimesh.load(meshdir / mesh_files[geom.meshname], force="mesh")
                local = mesh.vertices @ _quat_wxyz_to_mat(geom.quat).T + np.asarray(geom.pos)
                hulls.append(local @ rot.T + pos)
                weights.append(max(float(mesh.convex_hull.volume), 1e-9))
        if not hulls:
            raise ValueError(f"{self.object_xml}: no collision hulls found")
        lowest = min(h[:, 2].min() for h in hulls)
        shift = np.array([0.0, 0.0, TABLE_HEIGHT + DROP_CLEARANCE - lowest])
        hulls = [h + shift for h in hulls]
        masses = OBJECT_MASS * np.asarray(weights) / np.sum(weights)
        com = sum(m * h.mean(axis=0) for m, h in zip(masses, hulls)) / OBJECT_MASS
        root_pos, root_rot = body_pose(spec.worldbody.bodies[0].name)
        root_pos = root_pos + shift
        self._root_in_com = root_pos - com  # the object frame's origin in the (world-aligned) COM frame
        shapes = [p.createCollisionShape(p.GEOM_MESH, vertices=(h - com).tolist(), physicsClientId=cid) for h in hulls]
        n = len(shapes) - 1
        self.object = p.createMultiBody(
            baseMass=float(masses[0]), baseCollisionShapeIndex=shapes[0], basePosition=com.tolist(),
            baseOrientation=[0, 0, 0, 1], linkMasses=masses[1:].tolist(), linkCollisionShapeIndices=shapes[1:],
            linkVisualShapeIndices=[-1] * n, linkPositions=[[0, 0, 0]] * n, linkOrientations=[[0, 0, 0, 1]] * n,
            linkInertialFramePositions=[[0, 0, 0]] * n, linkInertialFrameOrientations=[[0, 0, 0, 1]] * n,
            linkParentIndices=[0] * n, linkJointTypes=[p.JOINT_FIXED] * n, linkJointAxis=[[0, 0, 1]] * n,
            physicsClientId=cid)

        # Clouds (parts.npz points are in their body's frame) -> world rest pose -> the object's COM frame.
        npz = np.load(self.object_xml.parent / "parts.npz")
        body_names = [str(b) for b in npz["body_names"]]
        poses = [body_pose(b) for b in body_names]

        def to_com(points, point_body):
            out = np.empty_like(points)
            for k, (pos, rot) in enumerate(poses):
                sel = point_body == k
                out[sel] = points[sel] @ rot.T + pos + shift - com
            return out

        part_names = [str(n) for n in npz["part_names"]]
        self.part = part or part_names[0]
        k = part_names.index(self.part)
        self.object_cloud = _resample(to_com(npz["object_points"], npz["object_point_body"]), CLOUD_POINTS, self.rng)
        self.part_cloud = _resample(to_com(npz["points"][k], npz["point_body"][k]), CLOUD_POINTS, self.rng)
        self.root_rot_in_com = root_rot  # (the COM frame is world-aligned at rest)

    # ------------------------------------------------------------------------------------------------------ stepping
    def _set_motors(self, arm_q, finger) -> None:
        p, cid = self.p, self.client
        for j, q in zip(ARM_JOINTS, arm_q):
            p.setJointMotorControl2(self.robot, j, p.POSITION_CONTROL, targetPosition=float(q), force=ARM_FORCE,
                                    positionGain=KP, physicsClientId=cid)
        for j in (LEFT_FINGER, RIGHT_FINGER):
            p.setJointMotorControl2(self.robot, j, p.POSITION_CONTROL, targetPosition=float(finger),
                                    force=FINGER_FORCE, positionGain=KP, physicsClientId=cid)

    def step_physics(self, tcp_pos, tcp_quat_xyzw, finger, ik: bool = True) -> None:
        """IK (link 11, 20 iterations, seeded from the current joints, no limits), motors, 12 physics steps."""
        p, cid = self.p, self.client
        if ik:
            rot = np.array(p.getMatrixFromQuaternion(tcp_quat_xyzw)).reshape(3, 3)
            target = np.asarray(tcp_pos) + TCP_OFFSET * rot[:, 2]  # TCP -> link-11 target
            q = p.calculateInverseKinematics(self.robot, EE_LINK, target.tolist(), list(tcp_quat_xyzw),
                                             maxNumIterations=20, physicsClientId=cid)
            self._set_motors(q[:7], finger)
        for _ in range(SUBSTEPS):
            p.stepSimulation(physicsClientId=cid)

    def tcp_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and quaternion (x, y, z, w): link 11 translated -0.05 along its z."""
        p = self.p
        state = p.getLinkState(self.robot, EE_LINK, computeForwardKinematics=True, physicsClientId=self.client)
        pos, quat = np.asarray(state[4]), np.asarray(state[5])
        rot = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return pos - TCP_OFFSET * rot[:, 2], quat

    def predicates(self, direction=(0.0, 1.0, 0.0), goal_pos=(0.0, 0.0, 0.1)) -> dict[str, bool]:
        """The spec-4 predicates the original's way, on 10,000-point NumPy clouds (TOUCHING without its step)."""
        p, cid = self.p, self.client
        pos, quat = p.getBasePositionAndOrientation(self.object, physicsClientId=cid)
        pos = np.asarray(pos)
        rot = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        object_cloud = self.object_cloud @ rot.T + pos  # update_part_pcds: every cloud follows the base pose
        part_cloud = self.part_cloud @ rot.T + pos
        origin = pos + rot @ self._root_in_com  # the object frame's origin (the original's "base position")
        tcp_pos, tcp_quat = self.tcp_pose()
        tcp_rot = np.array(p.getMatrixFromQuaternion(tcp_quat)).reshape(3, 3)

        on = len(p.getClosestPoints(self.table, self.object, 0.001, physicsClientId=cid)) > 0
        finger_q = p.getJointState(self.robot, LEFT_FINGER, physicsClientId=cid)[0]
        gripper_open = abs(finger_q - 0.04) < 0.005
        min_distance = float(np.linalg.norm(origin - tcp_pos)) > 0.05
        grasping = False
        for link in (LEFT_FINGER, RIGHT_FINGER):
            contacts = p.getContactPoints(bodyA=self.robot, linkIndexA=link, physicsClientId=cid)
            if not contacts:
                continue
            strong = any(c[9] > 20.0 for c in contacts)
            points = np.array([c[5] for c in contacts])  # contact positions on the finger
            dist = np.sqrt(((points[:, None, :] - part_cloud[None]) ** 2).sum(-1)).min()
            grasping |= bool(strong and dist < 0.003)
        v = part_cloud.mean(axis=0) - origin
        d = np.asarray(direction, float)
        facing = float(np.arccos(np.clip(v @ d / (np.linalg.norm(v) * np.linalg.norm(d) + 1e-12), -1, 1))) < 0.5
        tip = tcp_pos + FINGERTIP_OFFSET * tcp_rot[:, 2]
        touching_dist = float(np.sqrt(((part_cloud - tip) ** 2).sum(-1)).min()) < 0.01
        at_position = float(np.linalg.norm(origin - np.asarray(goal_pos))) < 0.02
        whole_mean = object_cloud.mean(axis=0)  # the whole-object cloud is transformed and used as the original does
        return {"on": on, "gripper_open": gripper_open, "min_distance": min_distance, "grasping": grasping,
                "facing": facing, "touching_distance": touching_dist, "at_position": at_position,
                "object_cloud_finite": bool(np.isfinite(whole_mean).all())}

    def step_like_the_original(self, tcp_pos, tcp_quat_xyzw=HOME_TCP_QUAT_XYZW, finger=panda.FINGER_OPEN):
        """One env step: IK + motors + 12 physics steps + the predicates; returns the predicates."""
        self.step_physics(tcp_pos, tcp_quat_xyzw, finger)
        return self.predicates()

    def close(self) -> None:
        if self.client is not None and self.p.isConnected(self.client):
            self.p.disconnect(self.client)
        self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def tcp_circle(steps: int, radius: float = 0.05, period_steps: int = 80) -> np.ndarray:
    """(steps, 3) TCP targets on a horizontal circle through the home TCP (home orientation kept)."""
    angle = 2 * np.pi * np.arange(1, steps + 1) / period_steps
    offset = radius * np.stack([np.cos(angle) - 1.0, np.sin(angle), np.zeros_like(angle)], axis=1)
    return HOME_TCP_POS + offset


def measure(steps: int = 200, repeats: int = 3, object_xml: str | Path | None = None,
            scene: PyBulletScene | None = None) -> PyBulletResult:
    """Env steps/s of `step_like_the_original` with the TCP sweeping a 5 cm circle; robot reset between repeats."""
    from partinstruct_mjx import paths

    own = scene is None
    scene = scene or PyBulletScene(object_xml or paths.default_object_xml())
    targets = tcp_circle(steps)
    rates = []
    try:
        for _ in range(repeats):
            scene.reset_robot()
            start = time.perf_counter()
            for target in targets:
                scene.step_like_the_original(target)
            rates.append(steps / (time.perf_counter() - start))
    finally:
        if own:
            scene.close()
    return PyBulletResult(float(np.median(rates)), (min(rates), max(rates)))


def measure_partinstruct_env(object_xml: str | Path, batch_size: int, steps: int = 200, repeats: int = 3,
                             num_threads: int | None = None) -> PyBulletResult:
    """Env steps/s (B x steps / s) of our `PartInstructEnv` on the C backend holding the TCP pose (IK, physics and
    the goal predicates every step), type-3 episode on the mug's handle; reset time is not counted."""
    import jax

    from partinstruct_mjx.env import EnvConfig, PartInstructEnv, hold_action
    from partinstruct_mjx.tasks.episodes import Episode
    from partinstruct_mjx.tasks.task_types import task_type

    chain = task_type(3).build_chain({"P1": "handle"}, {"D1": "left"})
    episode = Episode(obj_class="mug", obj_id="mug_000", ep_id=0, task_type=3, split="train", chain=tuple(chain),
                      task_instruction="t", skill_instructions=("a", "b"), obj_pose=(0, 0, 0, 1, 0, -0.03, 0),
                      obj_scale=1.0)
    rates = []
    with PartInstructEnv(object_xml, batch_size, EnvConfig(num_threads=num_threads)) as env:
        for r in range(repeats):
            state = env.reset(jax.random.PRNGKey(r), [episode] * batch_size)
            action = hold_action(state.obs["tcp_pose"])
            state = env.step(state, action)  # warm-up (compilation) outside the timing
            jax.block_until_ready(state.obs["tcp_pose"])
            start = time.perf_counter()
            for _ in range(steps):
                state = env.step(state, action)
            jax.block_until_ready(state.metrics["success"])
            rates.append(batch_size * steps / (time.perf_counter() - start))
        threads = len(getattr(env.backend, "_chunks", [])) or None
    result = PyBulletResult(float(np.median(rates)), (min(rates), max(rates)))
    measure_partinstruct_env.last_threads = threads
    return result


def markdown(pybullet: PyBulletResult, ours: dict[tuple[int, int], PyBulletResult], object_name: str) -> str:
    """Side-by-side table: PyBullet the original's way vs our env at (batch, physics threads), per core."""
    rows = [f"| PyBullet, the original's way | 1 | 1 | {pybullet.env_steps_per_s:,.0f} | "
            f"{pybullet.spread[0]:,.0f} - {pybullet.spread[1]:,.0f} | 1.00 |"]
    for (batch, threads), result in ours.items():
        ratio = result.env_steps_per_s / threads / pybullet.env_steps_per_s
        rows.append(f"| partinstruct-mjx env (mujoco backend) | {batch} | {threads} | {result.env_steps_per_s:,.0f} | "
                    f"{result.spread[0]:,.0f} - {result.spread[1]:,.0f} | {ratio:.2f} |")
    return (
        f"Panda + `{object_name}` (the same convex hulls in both engines). PyBullet: pybullet_data Panda, 1/240 s x 12 "
        "substeps, 150 solver iterations, calculateInverseKinematics (20 iterations) every step, predicates on "
        "10,000-point NumPy clouds every step (without the extra 12 physics steps the original's TOUCHING takes: "
        "generous to PyBullet); the TCP target circles 5 cm around home. Ours: `PartInstructEnv`, 5 ms x 10 substeps, "
        "batched JAX IK, the goals of a type-3 episode every step, holding the pose with the gripper open (the "
        "predicates of every part row are computed at once; the contact and fingertip searches run only when some "
        "finger presses the object or some gripper is closed, since GRASPING and TOUCHING are false otherwise, so "
        "they do not run here, while PyBullet's way searches the fingertip distance every step). 'Physics threads' "
        "counts MuJoCo's worker threads; XLA may run the JAX parts on the other core, so single-thread rows are an "
        "upper bound per core. Target (DESIGN.md): >= 5x per core.\n\n| engine | batch | physics threads | env steps/s (median) | range | per-core ratio |\n"
        "|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
