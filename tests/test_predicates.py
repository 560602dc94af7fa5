"""Predicates, spatial parts and task progress on hand-built states of a real built-in object (mug_000)."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from partinstruct_mjx import paths
from partinstruct_mjx.errors import TaskError
from partinstruct_mjx.sim.mujoco_backend import MujocoBackend
from partinstruct_mjx.sim.scene import SceneConfig, build_scene
from partinstruct_mjx.tasks import predicates, progress
from partinstruct_mjx.tasks.part_geometry import load_parts, spatial_masks
from partinstruct_mjx.tasks.task_types import TASK_TYPES, task_type
from partinstruct_mjx.tasks.vocabulary import DIRECTIONS, UNIT_DISTANCE, direction_vector

MUG = paths.assets_root() / "objects" / "mug" / "mug_000" / "object.xml"
UPDATE = jax.jit(progress.update, static_argnames="skill_mode")
INITIAL = jax.jit(progress.initial_task_state)


class World:
    """A settled mug scene whose object pose, contacts, TCP and gripper can be set by hand."""

    def __init__(self):
        self.scene = build_scene(SceneConfig(object_xml=str(MUG)))
        self.geo, self.names = load_parts(self.scene)
        with MujocoBackend(self.scene, 1) as backend:
            self.base = jax.tree_util.tree_map(lambda x: np.array(x[0]), backend.reset())
        self.origin = self.base.object_pos.copy()
        geoms = np.asarray(self.geo.geom_part)
        self.part_geom = {name: int(np.flatnonzero(geoms == i)[0]) for i, name in enumerate(self.names.semantic)
                          if (geoms == i).any()}

    def state(self, offset=(0.0, 0.0, 0.0), rotation=Rotation.identity(), grasp=None, touch=None,
              gripper=0.04, tcp=None, force=30.0):
        """A SceneState row: object moved by `offset` and turned by `rotation` about its origin; optionally the
        fingers pressing on part `grasp` with `force` N each, or closed with the fingertip on part `touch`."""
        s = jax.tree_util.tree_map(np.copy, self.base)
        body = self.scene.object_body
        quat = np.roll((rotation * Rotation.from_quat(np.roll(self.base.object_quat, -1))).as_quat(), 1)
        s.body_pos[body] = s.object_pos[:] = self.origin + np.asarray(offset)
        s.body_quat[body] = s.object_quat[:] = quat
        s.finger_qpos[:] = gripper
        s.tcp_pos[:] = s.object_pos + [0.0, 0.0, 0.3] if tcp is None else tcp
        s.tcp_quat[:] = [1.0, 0.0, 0.0, 0.0]
        if grasp is not None:
            point = self.part_point(s, grasp)
            geom = self.part_geom.get(grasp, self.part_geom["body"])
            s.contact_geom[:, 0] = geom
            s.contact_force[:, 0] = force
            s.contact_pos[:, 0] = point
            s.finger_qpos[:] = 0.02
        if touch is not None:
            s.finger_qpos[:] = 0.0
            s.tcp_pos[:] = self.part_point(s, touch) - [0.0, 0.0, predicates.FINGERTIP_OFFSET]
        return s

    def part_point(self, s, part, masks=None):
        masks = spatial_masks(predicates.object_points(s, self.geo)) if masks is None else masks
        points, valid = predicates.part_cloud(s, self.geo, masks, self.names.index(part))
        points, valid = np.asarray(points), np.asarray(valid)
        return points[valid].mean(axis=0) if part in ("handle", "body") else points[valid][0]

    def part_vector(self, s, part):
        masks = spatial_masks(predicates.object_points(s, self.geo))
        points, valid = predicates.part_cloud(s, self.geo, masks, self.names.index(part))
        return np.asarray(points)[np.asarray(valid)].mean(axis=0) - s.object_pos


@pytest.fixture(scope="module")
def world():
    return World()


def _masks(world, s):
    return spatial_masks(predicates.object_points(s, world.geo))


def test_on_table_and_lifted(world):
    assert predicates.on_table(world.state(), world.geo)
    assert not predicates.on_table(world.state(offset=(0, 0, 0.05)), world.geo)


def test_grasping_needs_force_and_the_named_part(world):
    geo, index = world.geo, world.names.index
    s = world.state(grasp="handle")
    masks = _masks(world, s)
    assert predicates.grasping(s, geo, masks, index("handle"))
    assert predicates.grasping(s, geo, masks, geo.whole)
    assert not predicates.grasping(s, geo, masks, index("body"))
    weak = world.state(grasp="handle", force=10.0)
    assert not predicates.grasping(weak, geo, masks, index("handle"))
    assert not predicates.grasping(world.state(), geo, masks, geo.whole)


def test_grasping_a_spatial_part_uses_contact_positions(world):
    geo = world.geo
    s = world.state(grasp="left")
    masks = _masks(world, s)
    assert predicates.grasping(s, geo, masks, world.names.index("left"))
    assert not predicates.grasping(s, geo, masks, world.names.index("right"))


def test_touching_needs_closed_fingers_near_the_part(world):
    geo = world.geo
    s = world.state(touch="handle")
    masks = _masks(world, s)
    assert predicates.touching(s, geo, masks, world.names.index("handle"))
    opened = s.replace(finger_qpos=np.array([0.02, 0.02]))
    assert not predicates.touching(opened, geo, masks, world.names.index("handle"))
    far = s.replace(tcp_pos=s.tcp_pos + [0.0, 0.0, 0.05])
    assert not predicates.touching(far, geo, masks, world.names.index("handle"))


@pytest.mark.parametrize("direction", ["left", "right", "front", "back"])
def test_facing_each_direction(world, direction):
    vector = world.part_vector(world.state(), "handle")
    turn = np.arctan2(DIRECTIONS[direction][1], DIRECTIONS[direction][0]) - np.arctan2(vector[1], vector[0])
    s = world.state(rotation=Rotation.from_euler("z", turn))
    masks = _masks(world, s)
    for other in ("left", "right", "front", "back", "top", "bottom"):
        result = predicates.facing(s, world.geo, masks, world.names.index("handle"), direction_vector(other))
        assert bool(result) == (other == direction), other


def test_release_gripper_open_and_distance(world):
    geo = world.geo
    free = world.state()
    masks = _masks(world, free)
    assert predicates.released(free, geo, masks)
    assert predicates.gripper_open(free) and predicates.min_distance(free)
    close = world.state(tcp=world.origin + [0.0, 0.0, 0.03])
    assert not predicates.min_distance(close) and not predicates.released(close, geo, masks)
    assert not predicates.released(world.state(grasp="body"), geo, masks)
    assert predicates.at_position(free, free.object_pos + [0.01, 0, 0], 0.02)
    assert not predicates.at_position(free, free.object_pos + [0.03, 0, 0], 0.02)


def test_spatial_parts_lie_on_their_side(world):
    s = world.state()
    points = np.asarray(predicates.object_points(s, world.geo))
    masks = np.asarray(_masks(world, s))
    mean = {w: points[masks[i]].mean(axis=0) for i, w in enumerate(("left", "right", "front", "back", "top",
                                                                     "bottom", "middle"))}
    assert mean["left"][1] > mean["right"][1] and mean["back"][0] > mean["front"][0]
    assert mean["top"][2] > mean["bottom"][2]
    assert all(masks.sum(axis=1) > 0)


def test_unknown_part_direction_and_task_type_are_named(world):
    with pytest.raises(TaskError, match="unknown part 'wheel'"):
        world.names.index("wheel")
    with pytest.raises(TaskError, match="unknown direction 'up'"):
        direction_vector("up")
    with pytest.raises(TaskError, match="task type '17' is out of range"):
        task_type("17")
    with pytest.raises(TaskError, match="unknown part 'wheel'"):
        progress.compile_episodes([(1, task_type(1).build_chain({"P1": "wheel"}, {}))], world.names)
    with pytest.raises(TaskError, match="does not fit task type 3"):
        progress.compile_episodes([(3, task_type(1).build_chain({"P1": "handle"}, {}))], world.names)


SLOTS = {"P1": "handle", "P2": "handle", "P3": "body"}


def _directions(type_id: int) -> dict:
    in_air = type_id in (8, 10, 11, 12, 16)
    return {"D1": "left", "D2": "top" if in_air else "front"}


def _script(world, chain):
    """States in which each skill of `chain` has just succeeded, one after another."""
    offset, rotation, states = np.zeros(3), Rotation.identity(), []
    held = None
    for step in chain:
        if step.name == "grasp_obj":
            held, touch = step.part, None
        elif step.name == "touch_obj":
            held, touch = None, step.part
        elif step.name == "move_gripper":
            offset = offset + UNIT_DISTANCE * direction_vector(step.direction)
            if step.put_down:
                offset[2] = 0.0
        elif step.name == "rotate_obj":
            current = world.part_vector(world.state(offset, rotation), step.part)
            target = direction_vector(step.direction)
            if offset[2] == 0.0:  # on the table: turn about the vertical only
                angle = np.arctan2(target[1], target[0]) - np.arctan2(current[1], current[0])
                turn = Rotation.from_euler("z", angle)
            else:
                turn, _ = Rotation.align_vectors([target], [current])
            rotation = turn * rotation
        elif step.name == "release_obj":
            held = touch = None
        if step.name == "release_obj":
            states.append(world.state(offset, rotation))
        elif step.name == "touch_obj" or (step.name == "move_gripper" and step.touching):
            states.append(world.state(offset, rotation, touch=touch))
        else:
            states.append(world.state(offset, rotation, grasp=held))
    return states


@pytest.mark.parametrize("type_id", sorted(TASK_TYPES))
def test_every_task_type_succeeds_in_skill_and_task_mode_on_its_script(world, type_id):
    chain = task_type(type_id).build_chain(SLOTS, _directions(type_id))
    compiled = progress.compile_episodes([(type_id, chain)], world.names)
    stack = lambda s: jax.tree_util.tree_map(lambda x: x[None], s)  # noqa: E731
    start = stack(world.state())
    skill = task = INITIAL(start, world.geo, compiled)
    assert not UPDATE(skill, start, world.geo, skill_mode=True).success[0]
    for number, state in enumerate(_script(world, chain), start=1):
        skill = UPDATE(skill, stack(state), world.geo, skill_mode=True)
        task = UPDATE(task, stack(state), world.geo, skill_mode=False)
        assert int(skill.skill_index[0]) == number, (type_id, chain[number - 1], np.asarray(skill.goals_met))
        assert float(skill.completion[0]) == pytest.approx(number / len(chain))
    assert skill.success[0]
    assert task.success[0], (type_id, np.asarray(task.goals_met), int(task.phase[0]))
    assert float(task.completion[0]) == 1.0


def test_task_mode_two_phases_complete_in_order(world):
    """Type 5: slide then release; the release alone (phase 2 before phase 1) is not success."""
    chain = task_type(5).build_chain({"P1": "handle"}, {"D1": "left"})
    compiled = progress.compile_episodes([(5, chain)], world.names)
    stack = lambda s: jax.tree_util.tree_map(lambda x: x[None], s)  # noqa: E731
    task = INITIAL(stack(world.state()), world.geo, compiled)
    task = UPDATE(task, stack(world.state()), world.geo, skill_mode=False)
    assert not task.success[0] and int(task.phase[0]) == 0
    moved = world.state(offset=(0, UNIT_DISTANCE, 0), grasp="handle")
    task = UPDATE(task, stack(moved), world.geo, skill_mode=False)
    assert int(task.phase[0]) == 1 and not task.success[0]
    assert float(task.completion[0]) == pytest.approx(3 / 4)
    task = UPDATE(task, stack(world.state(offset=(0, UNIT_DISTANCE, 0))), world.geo, skill_mode=False)
    assert task.success[0]


def _reference_facts(state, geo, masks):
    """The part facts one part row at a time with the single predicates (the reference `part_facts` must match)."""
    def row(part):
        points, valid = predicates.part_cloud(state, geo, masks, part)
        return (predicates.grasping(state, geo, masks, part), predicates.touching(state, geo, masks, part),
                predicates.masked_mean(points, valid))

    grasped, touched, centers = jax.vmap(row)(jax.numpy.arange(geo.points.shape[0]))
    return grasped, touched, centers, predicates.on_table(state, geo)


@pytest.mark.parametrize("obj_id, type_id, found", [("laptop_000", 3, 0),
                                                     pytest.param("stapler_004", 6, 1, marks=pytest.mark.slow)])
def test_part_facts_match_the_single_predicates_on_an_oracle_rollout(obj_id, type_id, found):
    """A grasp (articulated laptop) and a touch rollout: every part row, all at once and gated by batch, as one by
    one. `found` is the fact (0 grasped, 1 touched) the rollout must make true somewhere, so its search is tested."""
    from partinstruct_mjx.assets.catalog import load_catalog
    from partinstruct_mjx.env import EnvConfig, PartInstructEnv
    from partinstruct_mjx.oracle.rollout import OraclePolicy
    from partinstruct_mjx.tasks.episodes import generate_episodes

    root = paths.assets_root()
    episode = next(e for e in generate_episodes(load_catalog(root), root, 0, 1, ("train",))
                   if e.obj_id == obj_id and e.task_type == type_id)
    states = []
    with PartInstructEnv(root / "objects" / episode.obj_class / obj_id / "object.xml", 1, EnvConfig()) as env:
        state = env.reset(jax.random.PRNGKey(1), [episode])
        policy = OraclePolicy()
        policy.reset(env, state, jax.random.PRNGKey(1))
        while not state.done[0] and len(states) < 120:
            state = env.step(state, policy.act(env, state))
            states.append(jax.tree_util.tree_map(np.array, (state.data, state.task.masks)))
        geo = env.geometry
    data, masks = jax.tree_util.tree_map(lambda *x: np.concatenate(x), *states)
    reference = jax.jit(jax.vmap(_reference_facts, in_axes=(0, None, 0)))(data, geo, masks)
    single = jax.jit(jax.vmap(predicates.part_facts, in_axes=(0, None, 0)))(data, geo, masks)
    batched = jax.jit(predicates.batch_part_facts)(data, geo, masks)
    grasped, touched = np.asarray(reference[0]), np.asarray(reference[1])
    assert (grasped, touched)[found].any()
    idle = ~np.asarray(jax.vmap(predicates.pressing, in_axes=(0, None))(data, geo)).any(axis=1) & ~np.asarray(
        jax.vmap(predicates.fingers_closed)(data))
    assert 0 < idle.sum() < len(idle)
    idle_data = jax.tree_util.tree_map(lambda x: x[idle], data)
    skipped = jax.jit(predicates.batch_part_facts)(idle_data, geo, masks[idle])
    for facts, rows in ((single, slice(None)), (batched, slice(None)), (skipped, idle)):
        np.testing.assert_array_equal(facts.grasped, grasped[rows])
        np.testing.assert_array_equal(facts.touched, touched[rows])
        np.testing.assert_allclose(facts.centers, np.asarray(reference[2])[rows], atol=1e-6)
        np.testing.assert_array_equal(facts.on_table, np.asarray(reference[3])[rows])
    off = jax.numpy.asarray(False)  # no goal row reads a search: its facts are false or zero, labels still hold
    unread = jax.jit(predicates.batch_part_facts)(data, geo, masks, regions=off, tips=off, centers=off, table=off)
    spatial = (np.arange(len(grasped[0])) >= geo.num_semantic) & (np.arange(len(grasped[0])) < geo.whole)
    np.testing.assert_array_equal(unread.grasped, grasped & ~spatial)
    assert not np.asarray(unread.touched).any() and not np.asarray(unread.on_table).any()
    np.testing.assert_array_equal(unread.centers, 0.0)


ROTATION_TYPES = sorted(t for t in TASK_TYPES if any(s.name == "rotate_obj" for s in task_type(t).chain))


@pytest.mark.parametrize("type_id", [3] + ROTATION_TYPES)
def test_task_mode_keeps_a_rotation_types_spatial_parts_on_the_object(world, type_id):
    """Task mode resamples spatial parts every step, except for the types that turn the object (type 11 too,
    docs/differences.md #35): there 'the back' stays the region that was at the back, wherever it turns."""
    chain = task_type(type_id).build_chain(SLOTS, _directions(type_id))
    compiled = progress.compile_episodes([(type_id, chain)], world.names)
    stack = lambda s: jax.tree_util.tree_map(lambda x: x[None], s)  # noqa: E731
    task = INITIAL(stack(world.state()), world.geo, compiled)
    turned = world.state(rotation=Rotation.from_euler("z", np.pi / 2))
    task_after = UPDATE(task, stack(turned), world.geo, skill_mode=False)
    kept = bool(np.array_equal(np.asarray(task_after.masks), np.asarray(task.masks)))
    assert kept == (type_id in ROTATION_TYPES)
