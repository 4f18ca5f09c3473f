"""roboschool_humanoid.py: the numbers of Roboschool's rules (thresholds, ranges, sizes, the body's physics), each
probed on both sides of its value, so that a changed number fails; checked against hand computations from the
simulator's own state, not against the module's helpers. And benchmarks/roboschool_measures.py's knock-down window."""

import os
import re
import sys

import numpy as np
import pytest
from conftest import (
    JOINTS,
    PART_GEOMS,
    PART_ORIGINS,
    ROOT,
    ROW0,
    TASKS,
    body_xy,
    make,
    restart_potential,
    stand,
    step_from,
    torso_velocity,
    torso_z,
)

gym = pytest.importorskip("gymnasium")
mujoco = pytest.importorskip("mujoco")
DT = 0.0165
# Each motor's power: the torque at action 1 is 0.41 x this.
POWERS = dict(abdomen_z=100, abdomen_y=100, abdomen_x=100, right_shoulder1=75, right_shoulder2=75, right_elbow=75)
POWERS |= dict(left_shoulder1=75, left_shoulder2=75, left_elbow=75)
for _side in ("right", "left"):
    POWERS |= {f"{_side}_hip_x": 100, f"{_side}_hip_z": 100, f"{_side}_hip_y": 300, f"{_side}_knee": 200}


def frozen(task, seed=0):
    """An env with no gravity and no contacts: a body put at rest, its joints inside their limits, stays where it is."""
    env = make(task, seed)
    env.model.opt.gravity[:] = 0.0
    env.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    return env


def joint_qpos(env, name):
    return env.model.joint(name).qposadr[0]


def pose(env, z, **angles):
    """qpos of the body upright at (0, 0), its torso's Bullet frame (uwaist's centre) at height z, its joints at 0 (the
    knees bent 0.1 rad, inside their limits) but for `angles` (rad)."""
    qpos = env.data.qpos.copy()
    qpos[:7] = [0.0, 0.0, z, 1.0, 0.0, 0.0, 0.0]
    for name in JOINTS:
        qpos[joint_qpos(env, name)] = angles.get(name, -0.1 if name.endswith("knee") else 0.0)
    env.data.qpos[:] = qpos
    mujoco.mj_kinematics(env.model, env.data)
    qpos[2] += z - torso_z(env)
    return qpos


def joint_angles(env):
    return np.array([env.data.joint(name).qpos[0] for name in JOINTS])


def far_flag(env, distance=10.0):
    """The flag `distance` m ahead of the body along x, the potential the current state's."""
    env.bodies.target[0] = body_xy(env) + [distance, 0.0]
    env.data.mocap_pos[0, :2] = env.bodies.target[0]
    restart_potential(env)


@pytest.mark.parametrize("z, alive", [(0.79, 2.0), (0.77, -1.0)])
def test_alive_while_the_torso_frame_is_above_078_m(z, alive):
    """+2 while uwaist's centre is above 0.78 m; below, -1 and the end, though the torso's origin is 0.12 m higher."""
    env = frozen("HumanoidForward")
    _, _, terminated, _, info = step_from(env, pose(env, z), np.zeros(env.model.nv), np.zeros(17))
    assert torso_z(env) == pytest.approx(z, abs=1e-9) and env.data.body("torso").xpos[2] > 0.88
    assert info["reward_alive"] == alive and terminated == (alive < 0)


@pytest.mark.parametrize("z", [0.79, 0.81])
def test_flagrun_harder_is_on_the_ground_below_08_m(z):
    """Below 0.8 m: the leak is 1 + z / 0.8 (saturated at 2 above), the progress of a slide is not paid, the on-ground
    counter rises, and so no cube is thrown at the next throw step."""
    env = frozen("HumanoidFlagrunHarder")
    qvel = np.zeros(env.model.nv)
    qvel[0] = 1.0  # sliding toward the flag at 1 m/s
    env.set_state(pose(env, z), qvel)
    far_flag(env)
    before = np.linalg.norm(env.bodies.target[0] - body_xy(env))
    env.bodies.frame[0] = 119  # the next step is no throw step; the one after is (Roboschool's frame 120)
    _, _, terminated, _, info = env.step(np.zeros(17))
    after = np.linalg.norm(env.bodies.target[0] - body_xy(env))
    assert torso_z(env) == pytest.approx(z, abs=1e-9) and before - after == pytest.approx(DT, rel=1e-3)
    assert info["reward_alive"] == pytest.approx(1 + min(z, 0.8) / 0.8, abs=1e-9) and not terminated
    assert info["reward_progress"] == (
        pytest.approx(0.0, abs=1e-9) if z < 0.8 else pytest.approx((before - after) / DT)
    )
    info = env.step(np.zeros(17))[4]
    assert info["cubes_thrown"] == (0 if z < 0.8 else 1)


def test_the_body_xy_is_the_mean_of_29_parts():
    """The distance to the flag is measured from the mean x, y of the 12 links other than the torso's (their last geoms'
    centres where those are capsules, else the bodies' origins) and the 17 joints' anchors: not the 13 bodies' origins,
    nor with the torso's link, nor with the feet's and hands' spheres' centres."""
    env = frozen("HumanoidFlagrun", seed=3)
    model = env.model
    bodies = "lwaist pelvis right_thigh right_shin right_foot left_thigh left_shin left_foot right_upper_arm".split()
    bodies += "right_lower_arm left_upper_arm left_lower_arm".split()
    last_geoms = [model.geom(model.body(b).geomadr[0] + model.body(b).geomnum[0] - 1) for b in bodies]
    capsules = [geom.name for geom in last_geoms if geom.type == mujoco.mjtGeom.mjGEOM_CAPSULE]
    assert sorted(capsules) == sorted(PART_GEOMS)
    spheres = [geom for geom in last_geoms if geom.type != mujoco.mjtGeom.mjGEOM_CAPSULE]
    assert sorted(model.body(int(geom.bodyid[0])).name for geom in spheres) == sorted(PART_ORIGINS)
    angles = {name: 0.7 * env.model.joint(name).range.mean() for name in JOINTS}  # bent, inside the limits
    env.set_state(pose(env, 1.4, **angles), np.zeros(env.model.nv))
    env.bodies.target[0] = [3.0, -2.0]
    env.data.mocap_pos[0, :2] = env.bodies.target[0]
    restart_potential(env)
    info = env.step(np.zeros(17))[4]
    assert not info["flag_moved"]
    distance = np.linalg.norm(env.bodies.target[0] - body_xy(env))
    assert info["distance_to_target"] == pytest.approx(distance, abs=1e-9)
    thirteen = np.mean([env.data.body(name).xpos[:2] for name in ["torso", *bodies]], axis=0)
    with_torso = (body_xy(env) * 29 + env.data.geom("uwaist").xpos[:2]) / 30
    centres = [env.data.geom(geom.id).xpos[:2] - env.data.body(int(geom.bodyid[0])).xpos[:2] for geom in spheres]
    at_spheres = body_xy(env) + np.sum(centres, axis=0) / 29
    for other in (thirteen, with_torso, at_spheres):  # far enough from the rule's to fail a test that read them
        assert abs(np.linalg.norm(env.bodies.target[0] - other) - distance) > 1e-3


@pytest.mark.parametrize("distance, moved", [(0.99, True), (1.01, False)])
def test_the_flag_moves_when_the_body_comes_within_1_m(distance, moved):
    env = frozen("HumanoidFlagrun", seed=3)
    env.set_state(pose(env, 1.4), np.zeros(env.model.nv))
    env.bodies.target[0] = body_xy(env) + distance * np.array([0.6, -0.8])
    env.data.mocap_pos[0, :2] = env.bodies.target[0]
    restart_potential(env)
    info = env.step(np.zeros(17))[4]
    assert info["flag_moved"] == moved and info["flags_reached"] == int(moved)


def floor_contacts(env):
    """Whether each foot (right, left) touches the floor in the simulator's contacts, by name."""
    names = {(env.model.geom(a).name, env.model.geom(b).name) for a, b in env.data.contact.geom}
    return [float(("floor", foot) in names or (foot, "floor") in names) for foot in ("right_foot", "left_foot")]


def test_a_state_reads_the_feet_contacts_the_previous_step_left():
    """Roboschool reads the contacts after it has made the state: a step's state shows the floor contacts of the step
    before it."""
    env = make("HumanoidForward")
    raised = dict(left_hip_y=-1.0, left_knee=-1.5)  # the left foot up, the right one down
    poses = {"air": pose(env, 2.0), "right": pose(env, 1.4, **raised)}
    poses["left"] = pose(env, 1.4, **{name.replace("left", "right"): a for name, a in raised.items()})
    for name in ("right", "left"):  # the lower foot 2 cm into the floor
        env.data.qpos[:] = poses[name]
        mujoco.mj_kinematics(env.model, env.data)
        foot = "right_foot" if name == "right" else "left_foot"
        poses[name][2] -= env.data.geom(foot).xpos[2] - env.model.geom(foot).size[0] + 0.02
    contacts, states = [], []
    for name in ("air", "right", "air", "left", "left", "right", "air", "air"):
        stand(env, poses[name])
        states.append(env.step(np.zeros(17))[0][-2:])
        contacts.append(floor_contacts(env))
    assert contacts == [[0, 0], [1, 0], [0, 0], [0, 1], [0, 1], [1, 0], [0, 0], [0, 0]]
    np.testing.assert_array_equal(states, [[0, 0], *contacts[:-1]])


def test_a_step_is_4_physics_steps_of_00165_over_4_s():
    env = make("HumanoidForward")
    assert env.model.opt.timestep == pytest.approx(DT / 4, rel=1e-12)
    for _ in range(3):
        time = env.data.time
        env.step(np.zeros(17))
        assert (env.data.time - time) / env.model.opt.timestep == pytest.approx(4)
    assert env.data.time == pytest.approx(3 * DT) and env.dt == pytest.approx(DT)


def test_an_episode_is_truncated_at_step_1000():
    for task in TASKS:
        assert gym.make(f"roboschool_humanoid:{task}-v0").spec.max_episode_steps == 1000
    env = gym.make("roboschool_humanoid:HumanoidForward-v0")
    env.reset(seed=0)
    unwrapped = env.unwrapped
    unwrapped.model.opt.gravity[:] = 0.0  # a body that floats at rest: never a fall
    unwrapped.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    stand(unwrapped, pose(unwrapped, 1.4))
    ends = []
    for step in range(1, 1001):
        _, _, terminated, truncated, _ = env.step(np.zeros(17, np.float32))
        if terminated or truncated:
            ends.append((step, terminated, truncated))
    assert ends == [(1000, False, True)]


def test_the_joints_start_uniform_in_01_rad_at_rest():
    angles = []
    for task in TASKS:
        env = make(task)
        for seed in range(150):
            env.reset(seed=seed)
            angles.append(joint_angles(env))
            assert not env.data.qvel.any()
    angles = np.array(angles)
    assert np.abs(angles).max() <= 0.1 and angles.min() < -0.099 and angles.max() > 0.099
    assert np.all(np.abs(angles.mean(0)) < 0.015) and np.all(np.abs(angles.std(0) - 0.1 / np.sqrt(3)) < 0.006)


def test_the_flag_is_uniform_in_13125_by_625_m():
    """x uniform in [-13.125, 13.125], y in [-6.25, 6.25] (the marker, as the simulator holds it)."""
    env = make("HumanoidFlagrun")
    flags = []
    for seed in range(600):
        env.reset(seed=seed)
        flags.append(env.data.mocap_pos[0, :2].copy())
    (x_low, y_low), (x_high, y_high) = np.min(flags, 0), np.max(flags, 0)
    assert -13.125 <= x_low < -12.925 and 12.925 < x_high <= 13.125
    assert -6.25 <= y_low < -6.15 and 6.15 < y_high <= 6.25


class Ends:
    """A stand-in for the env's generator that draws the low (or the high) end of every range."""

    def __init__(self, high):
        self.high = high

    def uniform(self, low, high, size=None):
        return np.broadcast_to(np.asarray(high if self.high else low, float), size or np.shape(low)).copy()


def test_the_cube_is_01_m_of_06_kg_resting_at_minus_15_0_005():
    env = make("HumanoidFlagrunHarder")
    cube = env.model.body("cube")
    (geom,) = [env.model.geom(g) for g in range(env.model.ngeom) if env.model.geom_bodyid[g] == cube.id]
    assert geom.type[0] == mujoco.mjtGeom.mjGEOM_BOX and geom.size.tolist() == [0.05] * 3
    assert cube.mass[0] == pytest.approx(0.6, rel=1e-12)
    env.bodies.throw_cube(0)
    for seed in range(3):  # back at rest there at every reset
        env.reset(seed=seed)
        np.testing.assert_allclose(env.data.body("cube").xpos, [-1.5, 0.0, 0.05], atol=1e-12)
        np.testing.assert_array_equal(env.data.body("cube").xquat, [1.0, 0.0, 0.0, 0.0])
        np.testing.assert_array_equal(env.data.joint(cube.jntadr[0]).qvel, np.zeros(6))


@pytest.mark.parametrize("high", [False, True])
def test_the_cube_flies_from_4_m_and_1_m_up_at_20_to_30_m_s_toward_where_the_torso_frame_will_be(high):
    """From 4 m at a random angle and 1 m up from where the torso's Bullet frame will be (its position + its velocity x
    4 / speed), at speed 20-30 m/s toward there, plus noise uniform in +-1 m/s on each axis: here at the ends of the
    ranges."""
    env = make("HumanoidFlagrunHarder")
    qvel = np.zeros(env.model.nv)
    qvel[:6] = [1.0, -2.0, 0.5, 2.0, -1.0, 3.0]  # moving and spinning, in the air
    env.set_state(pose(env, 2.0), qvel)
    far_flag(env)
    env.bodies.frame[0] = 120
    env.bodies.rngs[0] = Ends(high)  # the rules draw from the body's generator, set to the env's at its reset
    info = env.step(np.zeros(17))[4]
    assert info["cubes_thrown"] == 1
    angle, speed, noise = (3.14, 30.0, 1.0) if high else (-3.14, 20.0, -1.0)
    velocity = torso_velocity(env)
    assert np.linalg.norm(velocity - env.data.qvel[:3]) > 0.2  # the frame's, not the origin's
    target = np.append(body_xy(env), torso_z(env)) + velocity * 4.0 / speed
    start = target + [4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.0]
    joint = env.data.joint(env.model.body("cube").jntadr[0])
    np.testing.assert_allclose(joint.qpos, [*start, 1.0, 0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(joint.qvel[:3], (target - start) / np.sqrt(17) * speed + noise, atol=1e-9)
    np.testing.assert_array_equal(joint.qvel[3:], np.zeros(3))


def test_electricity_costs_the_raw_action_and_the_motors_apply_the_clipped_one():
    env = make("HumanoidForward")
    action = np.tile([2.0, -1.5, 0.5, -3.0], 5)[:17]
    qpos = env.data.qpos.copy()
    _, _, _, _, info = step_from(env, qpos, np.zeros(env.model.nv), action)
    speeds = 0.1 * np.array([env.data.joint(n).qvel[0] for n in JOINTS])
    electricity = -2.0 * 4.25 * np.mean(np.abs(action * speeds)) - 0.1 * 4.25 * np.mean(action**2)
    assert info["reward_electricity"] == pytest.approx(electricity, rel=1e-9)
    for name, a in zip(JOINTS, np.clip(action, -1.0, 1.0), strict=True):
        torque = env.data.qfrc_actuator[env.model.joint(name).dofadr[0]]
        # Bullet's torque turns the joint about its axis as the xml writes it: on MuJoCo's unit axis, 1 / |axis| of it
        assert torque == pytest.approx(0.41 * POWERS[name] * a / np.linalg.norm(xml_axis(name)))


def test_the_state_is_clipped_to_5():
    env = make("HumanoidForward")
    speeds = dict(abdomen_z=80.0, abdomen_y=-80.0, abdomen_x=49.0, right_hip_x=-49.0)  # x 0.1: 8, -8, 4.9, -4.9
    qvel = np.zeros(env.model.nv)
    for name, speed in speeds.items():
        qvel[env.model.joint(name).dofadr[0]] = speed
    env.set_state(env.data.qpos.copy(), qvel)
    state = env.bodies.calc_state(ROW0)[0]
    np.testing.assert_allclose(state[9:16:2], [5.0, -5.0, 4.9, -4.9], rtol=1e-6)


def test_a_joint_is_at_its_limit_past_099_of_its_scaled_range():
    """-0.1 for each joint past 0.99 of its range scaled to [-1, 1]: 0.995 counts, 0.985 does not, on either side."""
    env = frozen("HumanoidForward")
    scaled = dict(abdomen_z=0.995, right_knee=-0.995, left_elbow=0.995, abdomen_y=0.985, right_hip_y=-0.985)
    scaled |= dict(left_shoulder1=0.985)
    angles = {
        name: np.mean(env.model.joint(name).range) + s * np.ptp(env.model.joint(name).range) / 2
        for name, s in scaled.items()
    }
    qpos = pose(env, 1.4, **angles)
    state, _, _, _, info = step_from(env, qpos, np.zeros(env.model.nv), np.zeros(17))
    assert info["reward_joints_at_limit"] == pytest.approx(-0.3)
    for name, s in scaled.items():
        assert env.data.joint(name).qpos[0] == pytest.approx(angles[name], abs=1e-12)  # where they were put
        assert state[8 + 2 * JOINTS.index(name)] == pytest.approx(s, abs=1e-6)


def xml_axis(name):
    """A joint's axis as gymnasium's humanoid.xml (and Roboschool's humanoid_symmetric.xml) write it."""
    import gymnasium.envs.mujoco

    path = os.path.join(os.path.dirname(gymnasium.envs.mujoco.__file__), "assets/humanoid.xml")
    return mujoco.MjSpec.from_file(path).joint(name).axis


def test_the_joints_are_roboschools():
    """No springs and no dampers; an armature only where the xml's axis is not of unit length (the shoulders and
    elbows: tests/test_bullet_body.py checks what it does); the hips' y to -120 degrees, other ranges gymnasium's."""
    import gymnasium.envs.mujoco

    env = make("HumanoidForward")
    path = os.path.join(os.path.dirname(gymnasium.envs.mujoco.__file__), "assets/humanoid.xml")
    gymnasium_model = mujoco.MjModel.from_xml_path(path)
    model = env.model
    long_axes = [name for name in JOINTS if abs(np.linalg.norm(xml_axis(name)) - 1.0) > 1e-9]
    assert len(long_axes) == 6
    for name in JOINTS:
        joint, theirs = model.joint(name), gymnasium_model.joint(name)
        assert joint.stiffness[0] == 0.0 and model.dof_damping[joint.dofadr[0]] == 0.0
        assert (model.dof_armature[joint.dofadr[0]] > 0) == (name in long_axes), name
        expected = np.radians([-120.0, 20.0]) if name.endswith("hip_y") else theirs.range
        np.testing.assert_allclose(joint.range, expected, rtol=1e-12)
    assert model.njnt == 1 + 17  # and the free joint


def test_every_geom_has_friction_08_in_3_dimensions():
    env = make("HumanoidForward")
    model = env.model
    body_geoms = [g for g in range(model.ngeom) if model.body(model.geom_bodyid[g]).name not in ("flag",)]
    assert len(body_geoms) == 1 + 17  # the floor and the body's
    for g in body_geoms:
        assert model.geom_friction[g][0] == 0.8 and model.geom_condim[g] == 3, model.geom(g).name
    for _ in range(60):  # the body falls onto the floor
        env.step(np.zeros(17))
        if env.data.ncon:
            break
    contact = env.data.contact
    assert model.geom("floor").id in contact.geom
    assert np.all(contact.friction[:, 0] == 0.8) and np.all(contact.dim == 3)


def overlap(env, geom1, geom2):
    """The simulator's contacts between two geoms, and their signed distance (negative: overlapping)."""
    model, data = env.model, env.data
    a, b = model.geom(geom1).id, model.geom(geom2).id
    pairs = [i for i, pair in enumerate(data.contact.geom) if {a, b} == set(pair)]
    return pairs, mujoco.mj_geomDistance(model, data, a, b, 1.0, np.zeros(6))


def test_no_contact_between_a_body_and_any_of_its_ancestors():
    """A foot folded into its own thigh touches nothing; one in the other leg's shin does, with friction 0.8."""
    env = make("HumanoidForward")
    folded = pose(env, 2.5, right_knee=-np.pi)  # past the knee's limit, the foot in the thigh
    env.set_state(folded, np.zeros(env.model.nv))
    pairs, distance = overlap(env, "right_foot", "right_thigh1")
    assert distance < -0.05 and not pairs
    crossed = dict(right_hip_x=np.radians(5), right_hip_z=np.radians(-60), right_hip_y=np.radians(-10))
    env.set_state(pose(env, 2.5, right_knee=np.radians(-40), **crossed), np.zeros(env.model.nv))
    pairs, distance = overlap(env, "right_foot", "left_shin1")
    assert distance < -0.05 and len(pairs) == 1
    assert env.data.contact.friction[pairs[0], 0] == 0.8 and env.data.contact.dim[pairs[0]] == 3
    # every pair of a body and an ancestor (a parent and its child MuJoCo skips by itself) is excluded, and no other
    model = env.model
    excluded = {(s >> 16, s & 0xFFFF) for s in model.exclude_signature}
    ancestry = set()
    for body in range(1, model.nbody):
        ancestor = model.body_parentid[model.body_parentid[body]]
        while ancestor != 0:
            ancestry.add((ancestor, body))
            ancestor = model.body_parentid[ancestor]
    assert excluded == ancestry and len(ancestry) == 21


def test_an_unstable_step_ends_the_episode_as_a_fall_that_pays_nothing():
    env = make("HumanoidForward")
    qvel = np.zeros(env.model.nv)
    qvel[env.model.joint("right_knee").dofadr[0]] = 1e11  # past MuJoCo's largest speed: it resets the body
    warnings = env.data.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number
    _, reward, terminated, _, info = step_from(env, env.data.qpos.copy(), qvel, np.ones(17))
    assert env.data.warning[mujoco.mjtWarning.mjWARN_BADQVEL].number > warnings
    names = ("alive", "progress", "electricity", "joints_at_limit", "feet_collision")
    assert [info[f"reward_{name}"] for name in names] == [-1.0, 0.0, 0.0, 0.0, 0.0]
    assert reward == -1.0 and terminated


@pytest.mark.parametrize("shape", [(16,), (18,), (1,), (), (17, 1)])
def test_a_wrong_shaped_action_is_refused(shape):
    env = make("HumanoidForward")
    message = re.escape(f"Action dimension mismatch. Expected (17,), found {shape}")
    with pytest.raises(ValueError, match=message):
        env.step(np.zeros(shape))


class Scripted(gym.Env):
    """An env that plays back one episode of (torso height, cubes thrown so far) per step, the flag never near."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, steps):
        self.steps = steps

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([1.4 - 0.8], np.float32), {}  # as the rules' state starts: the torso's height - 0.8

    def step(self, action):
        z, cubes = self.steps[self.t]
        self.t += 1
        info = dict(torso_z=z, cubes_thrown=cubes, distance_to_target=5.0, flag_moved=False, flags_reached=0)
        return np.zeros(1, np.float32), 1.0, self.t == len(self.steps), False, info


@pytest.mark.parametrize("after, knockdowns", [(30, 1), (31, 0)])
def test_a_fall_within_30_steps_of_a_throw_is_a_knock_down(monkeypatch, after, knockdowns):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import roboschool_measures as measures

    # the cube thrown at step 5; the body falls (below 0.8 m) `after` steps later, and lies there 2 steps
    steps = [(1.2, int(t >= 5)) for t in range(1, 5 + after)] + [(0.5, 1)] * 2
    env_id = f"ScriptedKnockdown{after}-v0"
    gym.register(env_id, entry_point=lambda: Scripted(steps))
    monkeypatch.setattr(measures, "policy", lambda checkpoint: (env_id, lambda obs: np.zeros(1), 0))
    try:
        (row,) = measures.play("unused.pt", 1)
    finally:
        del gym.registry[env_id]
    assert row["falls"] == 1 and row["cubes"] == 1 and row["knockdowns"] == knockdowns
