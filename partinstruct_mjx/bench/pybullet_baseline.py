"""The PyBullet side of the CPU benchmark: one env step done the original's way (spec 1.1-1.6, 4).

`PyBulletScene` builds, in a DIRECT client, a table plane at z = 0.06, the Panda from pybullet_data at the original's
base pose and home joints with the original's motor settings and finger gear constraint, and one object made of the
SAME convex hulls our converter wrote (`meshes/col_*.stl`), merged into one rigid object in the rest pose (the base
is the first hull; every further hull is a fixed-joint link, like the original's PartNet URDFs), 0.2 kg in all,
placed as our env places it (lowest point 5 mm above the table, then settled).

`step_like_the_original(tcp_pos, tcp_quat_xyzw, finger)` is one env step: `calculateInverseKinematics` on link 11
(20 iterations, seeded from the current state, no joint limits: spec 1.6 / 12 #2), position motors (arm force 2400,
gain 0.01; fingers force 5000, gain 0.01), 12 x `stepSimulation` at 240 Hz, then the original's per-step success
check of the current skill of the bench's type-3 episode (spec 5.2) on 10,000-point NumPy clouds: the object and
target-part clouds transformed by the base pose, then the skill's predicates in order, stopping at the first that
fails: GRASPING (finger contact forces > 20 N and a brute-force NumPy nearest-point search of the contact positions
against the part cloud, 3 mm) for the grasp, GRASPING(any) and AT_POSITION for the move, as our env evaluates the
current skill's goals. `predicates` computes every spec-4 predicate (for the tests); TOUCHING's extra
`world.step()` (12 more physics steps per evaluation in the original, spec 12 #3) does not arise in this chain.

Both engines run the same commanded workload (`workload`): from home the TCP moves above the mug's handle (untimed),
then repeats a 50-step grasp cycle, so finger contacts with force, a closed gripper and the searches that need them
occur as in an episode. `compare` times the engines in alternating repeats (PyBullet, ours, PyBullet, ours, ...),
so load on a shared machine affects both sides of each ratio alike.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from partinstruct_mjx.control.scripted_pick import top_down_quat
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
GRASP_TCP_POS = np.array([0.0, 0.012, 0.146])
"""Workload grasp: TCP over the mug_000 handle (object placed at (0, -0.03)), pads on its upper half."""
GRASP_TCP_QUAT = top_down_quat(0.0)
"""(w, x, y, z): approach axis down, fingers closing along x, across the handle."""
HOVER = 0.08
MOVE = np.array([0.0, 0.12, 0.0])
"""The bench episode's move: 0.12 m (the original's UNIT) to the left (+y)."""
"""Height of the cycle's hover pose above the grasp pose (the open fingers clear the handle)."""
CYCLE = 50
APPROACH_STEPS, APPROACH_HOLD = 60, 40


@dataclass(frozen=True)
class PyBulletResult:
    env_steps_per_s: float
    """Median over repeats (one process, one core)."""
    spread: tuple[float, float]
    """Slowest and fastest repeat, env steps/s."""
    ratio: tuple[float, float, float] | None = None
    """Per-core ratio to the PyBullet repeat run just before each repeat: median, lowest, highest (ours only)."""


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
        self._reset_robot()
        gear = p.createConstraint(self.robot, LEFT_FINGER, self.robot, RIGHT_FINGER, p.JOINT_GEAR, [1, 0, 0],
                                  [0, 0, 0], [0, 0, 0], physicsClientId=cid)
        p.changeConstraint(gear, gearRatio=-1, erp=0.1, maxForce=50, physicsClientId=cid)
        for link in range(-1, p.getNumJoints(self.robot, physicsClientId=cid)):
            p.changeDynamics(self.robot, link, linearDamping=0, angularDamping=0, physicsClientId=cid)
        p.setCollisionFilterPair(self.robot, self.robot, LEFT_FINGER, RIGHT_FINGER, 0, physicsClientId=cid)
        self._build_object(part)
        for _ in range(settle_steps):
            self.step_physics(HOME_TCP_POS, HOME_TCP_QUAT_XYZW, panda.FINGER_OPEN, ik=False)
        self._settled = p.getBasePositionAndOrientation(self.object, physicsClientId=cid)

    # ----------------------------------------------------------------------------------------------------- building
    def reset(self) -> None:
        """The robot at home (as built) and the object at its settled pose, both at rest."""
        p, cid = self.p, self.client
        self._reset_robot()
        p.resetBasePositionAndOrientation(self.object, *self._settled, physicsClientId=cid)
        p.resetBaseVelocity(self.object, [0, 0, 0], [0, 0, 0], physicsClientId=cid)
        self.skill, self.skill_start = 0, self._posed_clouds()[2]

    def _reset_robot(self) -> None:
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

    def _posed_clouds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The object and target-part clouds moved to the base pose (the original's update_part_pcds, every step)
        and the object frame's origin (the original's "base position")."""
        p, cid = self.p, self.client
        pos, quat = p.getBasePositionAndOrientation(self.object, physicsClientId=cid)
        pos = np.asarray(pos)
        rot = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        return self.object_cloud @ rot.T + pos, self.part_cloud @ rot.T + pos, pos + rot @ self._root_in_com

    def _grasping(self, cloud: np.ndarray) -> bool:
        """GRASPING: a finger contact over 20 N within 3 mm of `cloud` (brute-force NumPy nearest point)."""
        p, cid = self.p, self.client
        grasping = False
        for link in (LEFT_FINGER, RIGHT_FINGER):
            contacts = p.getContactPoints(bodyA=self.robot, linkIndexA=link, physicsClientId=cid)
            if not contacts:
                continue
            strong = any(c[9] > 20.0 for c in contacts)
            points = np.array([c[5] for c in contacts])  # contact positions on the finger
            dist = np.sqrt(((points[:, None, :] - cloud[None]) ** 2).sum(-1)).min()
            grasping |= bool(strong and dist < 0.003)
        return grasping

    def predicates(self, direction=(0.0, 1.0, 0.0), goal_pos=(0.0, 0.0, 0.1)) -> dict[str, bool]:
        """All spec-4 predicates the original's way, on 10,000-point NumPy clouds (TOUCHING without its step)."""
        p, cid = self.p, self.client
        object_cloud, part_cloud, origin = self._posed_clouds()
        tcp_pos, tcp_quat = self.tcp_pose()
        tcp_rot = np.array(p.getMatrixFromQuaternion(tcp_quat)).reshape(3, 3)
        on = len(p.getClosestPoints(self.table, self.object, 0.001, physicsClientId=cid)) > 0
        finger_q = p.getJointState(self.robot, LEFT_FINGER, physicsClientId=cid)[0]
        v = part_cloud.mean(axis=0) - origin
        d = np.asarray(direction, float)
        tip = tcp_pos + FINGERTIP_OFFSET * tcp_rot[:, 2]
        return {"on": on, "gripper_open": abs(finger_q - 0.04) < 0.005,
                "min_distance": float(np.linalg.norm(origin - tcp_pos)) > 0.05, "grasping": self._grasping(part_cloud),
                "facing": float(np.arccos(np.clip(v @ d / (np.linalg.norm(v) * np.linalg.norm(d) + 1e-12), -1, 1)))
                < 0.5,
                "touching_distance": float(np.sqrt(((part_cloud - tip) ** 2).sum(-1)).min()) < 0.01,
                "at_position": float(np.linalg.norm(origin - np.asarray(goal_pos))) < 0.02,
                "object_cloud_finite": bool(np.isfinite(object_cloud.mean(axis=0)).all())}

    def skill_check(self) -> bool:
        """The current skill's success check of the bench's type-3 episode, as the original's
        `_check_if_done_skill` runs it after every step (spec 5.2): the clouds follow the base pose, then the
        skill's predicates in order, stopping at the first that fails. grasp(handle): GRASPING(handle); then
        move(left, grasping): GRASPING(any), AT_POSITION(object, start + 0.12 m left, 0.05). A met skill hands over
        to the next and records the object's position."""
        object_cloud, part_cloud, origin = self._posed_clouds()
        if self.skill == 0:
            done = self._grasping(part_cloud)
        else:
            done = self._grasping(object_cloud) and float(np.linalg.norm(origin - self.skill_start - MOVE)) < 0.05
        if done:
            self.skill, self.skill_start = min(self.skill + 1, 1), origin
        return done

    def step_like_the_original(self, tcp_pos, tcp_quat_xyzw=HOME_TCP_QUAT_XYZW, finger=panda.FINGER_OPEN) -> bool:
        """One env step: IK + motors + 12 physics steps + the current skill's check; returns whether it is met."""
        self.step_physics(tcp_pos, tcp_quat_xyzw, finger)
        return self.skill_check()

    def close(self) -> None:
        if self.client is not None and self.p.isConnected(self.client):
            self.p.disconnect(self.client)
        self.client = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def approach() -> tuple[np.ndarray, np.ndarray]:
    """Untimed lead-in of the workload: (steps, 3) TCP targets from home to the hover pose over APPROACH_STEPS,
    then held for APPROACH_HOLD, and (steps,) finger targets (open)."""
    hover = GRASP_TCP_POS + [0.0, 0.0, HOVER]
    alpha = np.minimum(np.arange(1, APPROACH_STEPS + APPROACH_HOLD + 1) / APPROACH_STEPS, 1.0)[:, None]
    return HOME_TCP_POS + alpha * (hover - HOME_TCP_POS), np.full(len(alpha), panda.FINGER_OPEN)


def workload(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(steps, 3) TCP targets and (steps,) finger targets of the timed grasp cycle (orientation GRASP_TCP_QUAT).

    Each CYCLE of 50 steps: 10 open, descending from the hover pose to the grasp pose; 20 closed on the handle;
    10 open, rising back; 10 closed in the air at the hover pose (the fingers meet, as for a touch).
    """
    k = np.arange(steps) % CYCLE
    height = np.select([k < 10, k < 30, k < 40], [HOVER * (9 - k) / 10, 0.0 * k, HOVER * (k - 29) / 10], HOVER)
    closed = ((k >= 10) & (k < 30)) | (k >= 40)
    return GRASP_TCP_POS + height[:, None] * [0.0, 0.0, 1.0], np.where(closed, panda.FINGER_CLOSED, panda.FINGER_OPEN)


def pybullet_rate(scene: PyBulletScene, steps: int) -> float:
    """Env steps/s of `step_like_the_original` over the timed workload, after a reset and the untimed approach."""
    quat = np.roll(GRASP_TCP_QUAT, -1)
    scene.reset()
    for target, finger in zip(*approach()):
        scene.step_like_the_original(target, quat, finger)
    targets, fingers = workload(steps)
    start = time.perf_counter()
    for target, finger in zip(targets, fingers):
        scene.step_like_the_original(target, quat, finger)
    return steps / (time.perf_counter() - start)


def bench_episode():
    """The type-3 episode our env runs (grasp the mug's handle, move it left), object at (0, -0.03)."""
    from partinstruct_mjx.tasks.episodes import Episode
    from partinstruct_mjx.tasks.task_types import task_type

    chain = task_type(3).build_chain({"P1": "handle"}, {"D1": "left"})
    return Episode(obj_class="mug", obj_id="mug_000", ep_id=0, task_type=3, split="train", chain=tuple(chain),
                   task_instruction="t", skill_instructions=("a", "b"), obj_pose=(0, 0, 0, 1, 0, -0.03, 0),
                   obj_scale=1.0)


def _env_actions(targets: np.ndarray, fingers: np.ndarray, batch_size: int) -> np.ndarray:
    """(steps, B, 7) Euler actions of TCP targets at GRASP_TCP_QUAT with finger targets, the same for every scene."""
    import jax.numpy as jnp

    from partinstruct_mjx.control.rotations import quat_to_euler_xyz

    euler = np.asarray(quat_to_euler_xyz(jnp.asarray(GRASP_TCP_QUAT, jnp.float32)))
    rows = np.concatenate([targets, np.broadcast_to(euler, (len(targets), 3)), fingers[:, None]], axis=1)
    return np.repeat(rows[:, None], batch_size, axis=1).astype(np.float32)


def env_rate(env, steps: int, key) -> float:
    """Env steps/s (B x steps / s) of our `PartInstructEnv` over the timed workload, after a reset and the untimed
    approach; the type-3 episode's goals are evaluated every step."""
    import jax

    state = env.reset(key, [bench_episode()] * env.batch_size)
    for action in _env_actions(*approach(), env.batch_size):
        state = env.step(state, action)
    actions = _env_actions(*workload(steps), env.batch_size)
    jax.block_until_ready(state.metrics["success"])
    start = time.perf_counter()
    for action in actions:
        state = env.step(state, action)
    jax.block_until_ready(state.metrics["success"])
    return env.batch_size * steps / (time.perf_counter() - start)


def compare(object_xml: str | Path, configs: list[tuple[int, int]], steps: int = 200, repeats: int = 3
            ) -> tuple[PyBulletResult, dict[tuple[int, int], PyBulletResult]]:
    """PyBullet and our env at each (batch, physics threads) of `configs` on the workload, in alternating repeats:
    every repeat of a configuration directly follows a PyBullet repeat and is compared with it."""
    import jax

    from partinstruct_mjx.env import EnvConfig, PartInstructEnv

    envs = {c: PartInstructEnv(object_xml, c[0], EnvConfig(num_threads=c[1])) for c in configs}
    pybullet, ours = [], {c: [] for c in configs}
    try:
        with PyBulletScene(object_xml) as scene:
            for c, env in envs.items():
                env_rate(env, 1, jax.random.PRNGKey(0))  # compilation outside the timing
            for r in range(repeats):
                for c, env in envs.items():
                    pybullet.append(pybullet_rate(scene, steps))
                    ours[c].append((env_rate(env, steps, jax.random.PRNGKey(r)), pybullet[-1]))
    finally:
        for env in envs.values():
            env.close()
    results = {}
    for (batch, threads), pairs in ours.items():
        rates = [rate for rate, _ in pairs]
        ratios = [rate / threads / base for rate, base in pairs]
        results[batch, threads] = PyBulletResult(float(np.median(rates)), (min(rates), max(rates)),
                                                 (float(np.median(ratios)), min(ratios), max(ratios)))
    return PyBulletResult(float(np.median(pybullet)), (min(pybullet), max(pybullet))), results


def markdown(pybullet: PyBulletResult, ours: dict[tuple[int, int], PyBulletResult], object_name: str,
             steps: int) -> str:
    """Side-by-side table: PyBullet the original's way vs our env at (batch, physics threads), per core."""
    rows = [f"| PyBullet, the original's way | 1 | 1 | {pybullet.env_steps_per_s:,.0f} | "
            f"{pybullet.spread[0]:,.0f} - {pybullet.spread[1]:,.0f} | 1.00 | |"]
    for (batch, threads), result in ours.items():
        ratio, low, high = result.ratio
        rows.append(f"| partinstruct-mjx env (mujoco backend) | {batch} | {threads} | {result.env_steps_per_s:,.0f} | "
                    f"{result.spread[0]:,.0f} - {result.spread[1]:,.0f} | {ratio:.2f} | {low:.2f} - {high:.2f} |")
    return (
        f"Panda + `{object_name}` (the same convex hulls in both engines). Workload, commanded identically in both "
        f"engines: the TCP (top-down, fingers closing across the handle) moves from home to {HOVER * 100:g} cm "
        f"above a grasp pose on the mug's handle ({APPROACH_STEPS + APPROACH_HOLD} untimed steps), then {steps} timed "
        f"steps of a {CYCLE}-step cycle: 10 steps open descending to the grasp pose, 20 closed on the handle, 10 open "
        "rising back, 10 closed in the air at the hover pose. The gripper is commanded closed for 30 of every 50 "
        "steps; both fingers press the handle with > 20 N on about 6 of the 20 closed steps. PyBullet: pybullet_data "
        "Panda, 1/240 s x 12 substeps, 150 solver iterations, calculateInverseKinematics (20 iterations) every step, "
        "then the original's check of the current skill (spec 5.2) on 10,000-point NumPy clouds every step: both "
        "clouds moved to the object's pose, GRASPING of the handle (the contact search whenever a finger touches "
        "something), then for the move GRASPING(any) and AT_POSITION. Ours: "
        "`PartInstructEnv`, 5 ms x 10 substeps, batched JAX IK, the goals of the same type-3 episode (grasp the "
        "handle, move it left) every step, each part-fact search only when a current goal reads it. The engines run "
        "in alternating repeats (PyBullet, then one configuration of "
        "ours, and again); each per-core ratio is ours over the PyBullet repeat just before it, median and range "
        "over repeats. 'Physics threads' counts MuJoCo's worker threads; XLA may run the JAX parts on the other "
        "core, so single-thread rows are an upper bound per core. Target (DESIGN.md): >= 5x per core.\n\n"
        "| engine | batch | physics threads | env steps/s (median) | range | per-core ratio (median) | ratio range |\n"
        "|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
