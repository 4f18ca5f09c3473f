"""The PPO paper's three humanoid tasks (§6.3, Figure 4), with Roboschool's rules, on MuJoCo.

The paper ran RoboschoolHumanoid, RoboschoolHumanoidFlagrun and RoboschoolHumanoidFlagrunHarder: Roboschool's first
release (openai/roboschool at 911f7cd, May 2017, its "-v0" tasks) on its own Bullet build, which no longer installs.
This module rebuilds them on MuJoCo with that commit's rules and body, and registers them with gymnasium; the ids drop
"Roboschool", whose engine this is not. No script imports it: gymnasium's `module:id` form loads it by name, so

    python ppo_continuous.py --env-id roboschool_humanoid:HumanoidFlagrun-v0
    torchrun --standalone --nproc-per-node 2 ppo_continuous.py --env-id roboschool_humanoid:HumanoidFlagrunHarder-v0

Each id has its own vector env, which ppo_continuous.py takes through gym.make_vec: the rules computed once over N
bodies of one model, each in its own MjData, with the same episodes as N single envs of the same seeds (one: N = 1).

The body is humanoid_symmetric.xml as Roboschool's Bullet read and moved it, made with MjSpec from gymnasium's
humanoid.xml and measured against PyBullet 3.2.7, which loads the same file (benchmarks/bullet_body.py): friction 0.8,
hips to -120 degrees, no springs, no contact between a part and its ancestors, and bullet_body()'s masses and joints.
Bullet put a link's frame at its centre of mass, and a massless link at each joint: the rules' "torso" is that of the
torso (0.12 m below MuJoCo's origin), the body's parts the 12 other links and 17 joints'.

The rules (each step is 4 physics steps of 0.0165/4 s, an episode 1,000 steps):
- State, 44 numbers clipped to [-5, 5]: the torso's height above 0.8 m; sin and cos of the angle from the torso's
  heading (yaw) to the target; the torso's velocity in the heading's frame x 0.3; roll and pitch; each of the 17
  joints' position scaled to [-1, 1] between its limits and its speed x 0.1; the two feet's contact with the floor, as
  the previous step left it (Roboschool reads the contacts after it has made the state).
- Reward, the sum of: alive, +2 while the torso is above 0.78 m, else -1 and the episode ends; progress, the change of
  the potential -(distance to the target) / dt, the distance measured from the mean x, y of the 29 parts; electricity,
  -2 x 4.25 x mean |action x scaled joint speed|, and stall torque, -0.1 x 4.25 x mean action^2; -0.1 for each joint
  past 0.99 of its scaled range; -1 for each foot touching anything but the floor. Each motor's torque is
  0.41 x its power (100 for the abdomen and the hips' x and z, 300 for the hips' y, 200 for the knees, 75 for the
  arms) x the action clipped to [-1, 1]. Joints start uniform in +-0.1 rad, at rest, the torso at (0, 0, 1.4).
- HumanoidForward-v0: the target 1 km ahead, along x.
- HumanoidFlagrun-v0: a uniform random heading at the start; the flag uniform in [-13.125, 13.125] x [-6.25, 6.25] m,
  moved when the body comes within 1 m of it or after 200 steps, and the potential reset to the new flag's at a move,
  so that a move pays no jump.
- HumanoidFlagrunHarder-v0: Flagrun, with a quarter of the electricity cost; half the starts lie on the front or the
  back; every 30 steps after step 100, while the body stands, a 0.1 m cube of 0.6 kg flies from 4 m, 1 m up, at
  20-30 m/s toward where the torso will be, plus noise; the alive bonus becomes the "potential leak"
  1 + clip(z, 0, 0.8) / 0.8 and the potential gains 100 x that leak, so that getting up pays 100; progress made while
  the torso is below 0.8 m (crawling) is not paid; the episode ends after 170 steps on the ground (a counter that
  rises each step below 0.8 m and falls each step above).

Where ours differs from Roboschool, judge the comparison with Figure 4 by these:
- The engine: MuJoCo (implicitfast and Newton) against Bullet's multibody: contacts, joint limits and friction (Bullet
  multiplies two 0.8s into 0.64; MuJoCo takes the larger) act differently, the shoulders' and elbows' long axes are
  emulated, not reproduced, and Bullet's damping of each link's own motion is left out (with it MuJoCo comes no
  nearer). From the same states under the same actions, the joints part by an rms of 0.07 rad after 5 steps and 0.38
  after 20 (the earlier body's: 0.46 and 0.76; Bullet's from itself: 0 and 0.01), the torso by 0.01 m and 0.09 m
  (benchmarks/results/bullet/distances.md). A step MuJoCo finds unstable ends the episode as a fall.
- Random numbers come from gymnasium's generator, so no episode is Roboschool's, draw for draw. The flag is a marker.
"""

import os

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium.envs.mujoco import MujocoEnv

FRAME_SKIP = 4
DT = 0.0165  # seconds a step: 4 physics steps of 0.0165 / 4
# Roboschool's motors, in the order of the model's joints (and so of the action): (joint, power).
MOTORS = [("abdomen_z", 100), ("abdomen_y", 100), ("abdomen_x", 100)]
MOTORS += [("right_hip_x", 100), ("right_hip_z", 100), ("right_hip_y", 300), ("right_knee", 200)]
MOTORS += [("left_hip_x", 100), ("left_hip_z", 100), ("left_hip_y", 300), ("left_knee", 200)]
MOTORS += [("right_shoulder1", 75), ("right_shoulder2", 75), ("right_elbow", 75)]
MOTORS += [("left_shoulder1", 75), ("left_shoulder2", 75), ("left_elbow", 75)]
POWER = 0.41
STIFF = [0.01, 1.0]  # joint limits' and contacts' time constant (s) and damping ratio (MuJoCo's default: 0.02, 1)
# Bullet's inertia of each body (kg m^2, about its centre of mass, on the body's axes), the box its importer put around
# the body's geoms, as PyBullet 3.2.7 reports it (tests/test_bullet_body.py checks these against it).
BULLET_INERTIA = dict(torso=(0.281773, 0.221499, 0.132127), lwaist=(0.0135717, 0.00542867, 0.0135717))
BULLET_INERTIA |= dict(pelvis=(0.125487, 0.0745425, 0.125487), thigh=(0.132930, 0.131307, 0.0333019))
BULLET_INERTIA |= dict(shin=(0.0597453, 0.0597453, 0.0145519), foot=(0.00662680,) * 3)
BULLET_INERTIA |= dict(upper_arm=(0.0283491,) * 3, lower_arm=(0.0186898,) * 3)
# 17 joints, of which about 4 matter for walking: the costs are scaled by 17 / 4 = 4.25.
ELECTRICITY_COST = -2.0 * 4.25
STALL_TORQUE_COST = -0.1 * 4.25
JOINTS_AT_LIMIT_COST = -0.1
FOOT_COLLISION_COST = -1.0
INITIAL_Z = 0.8  # the state's height is the torso's above this
# Half the stadium of Roboschool's scene (105 x 50 m, scaled by 0.25), and half of that again: "more compact".
FLAG_HALF = np.array([105 * 0.25 * 0.5, 50 * 0.25 * 0.5])  # x, y
FLAG_TIMEOUT = 200
CAMERA_BACK, CAMERA_SIDE, CAMERA_UP, CAMERA_LOOK = 3.5, 1.5, 2.0, 3.0  # m: the film's camera from the body, its aim
# MuJoCo's warnings of an unstable simulation (bad qpos, qvel, qacc), after each of which it resets the state.
UNSTABLE = slice(int(mujoco.mjtWarning.mjWARN_BADQPOS), int(mujoco.mjtWarning.mjWARN_BADQACC) + 1)
BODIES = "torso lwaist pelvis right_thigh right_shin right_foot left_thigh left_shin left_foot".split()
BODIES += "right_upper_arm right_lower_arm left_upper_arm left_lower_arm".split()


def humanoid_spec(cube):
    """Gymnasium's humanoid.xml, changed with MjSpec into Roboschool's body, timestep and motors, with a flag marker on
    a mocap body, the film's camera, and for FlagrunHarder the cube on a free joint."""
    import gymnasium.envs.mujoco

    spec = mujoco.MjSpec.from_file(os.path.join(os.path.dirname(gymnasium.envs.mujoco.__file__), "assets/humanoid.xml"))
    spec.option.timestep = DT / FRAME_SKIP
    # MuJoCo's implicitfast integrator and its default Newton solver, where gymnasium's file asks for RK4 and PGS:
    # Bullet too steps with a semi-implicit Euler, and Newton solves the same contact problem in fewer iterations.
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    # humanoid_symmetric.xml: friction 0.8 on every geom (condim 3, body parts too), and hips' y to -120 degrees.
    for geom in spec.geoms:
        geom.condim = 3
        geom.friction = [0.8, 0.1, 0.1]
    for side in ("right", "left"):
        spec.joint(f"{side}_hip_y").range = [-120.0, 20.0]  # degrees, as the file's compiler reads angles
    bullet_body(spec)
    # Roboschool loaded the body so that a link never touches any of its ancestors; MuJoCo skips only the parent.
    for body in spec.bodies:
        ancestor = body.parent.parent if body.parent else None
        while ancestor is not None and ancestor.name != "world":
            spec.add_exclude(bodyname1=ancestor.name, bodyname2=body.name)
            ancestor = ancestor.parent
    spec.geom("floor").size[:2] *= 10  # drawn 400 m wide, not 40: a 1,000-step forward walk goes further
    spec.material("MatPlane").texrepeat *= 10  # the same squares; a plane's size changes only what is drawn
    for actuator in list(spec.actuators):
        spec.delete(actuator)
    for joint, power in MOTORS:
        motor = spec.add_actuator(name=joint, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        motor.gear[0] = POWER * power / np.linalg.norm(spec.joint(joint).axis)  # Bullet's axis as written: bullet_body
        motor.ctrllimited = True
        motor.ctrlrange = [-1.0, 1.0]
    spec.delete(spec.camera("track"))
    spec.worldbody.add_camera(name="track", fovy=60.0)  # render() places it behind the body, facing the flag
    flag = spec.worldbody.add_body(name="flag", mocap=True)
    marker = dict(contype=0, conaffinity=0, rgba=[0.9, 0.2, 0.2, 1.0])
    flag.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, 0, 0, 1.5], size=[0.03, 0, 0], **marker)
    flag.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[0, 0, 1.5], size=[0.2, 0, 0], **marker)
    if cube:  # Roboschool's cube.urdf: a 0.1 m box of 0.6 kg, resting at (-1.5, 0) until it is thrown
        body = spec.worldbody.add_body(name="cube", pos=[-1.5, 0.0, 0.05])
        body.add_freejoint(name="cube")
        box = dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.05] * 3, mass=0.6, solref=STIFF)
        body.add_geom(rgba=[1.0, 0.6, 0.1, 1.0], **box)
    return spec


def bullet_body(spec):
    """The body as Roboschool's Bullet built and moved it (benchmarks/bullet_distances.py measures each choice):
    - no dampers and no armature: its importer read none;
    - each body's centre of mass at the centre of its last geom if that is a capsule, else at its origin, with the
      inertia of the box Bullet put around its geoms (BULLET_INERTIA) and the mass of its geoms;
    - a joint turns about its axis as the xml writes it, unnormalized: at a joint speed u its link turns at |a| u while
      its angle moves at u, so that a motor moves |a|^2 times the inertia, and outside forces act |a| times as much.
      The motor's gear divided by |a| (MOTORS' loop) and an armature of |a| - 1 times the inertia about the axis that
      the free torso does not take up (at the xml's pose) match both, for the shoulders and elbows (|a| = 2^0.5, 6^0.5);
    - joint limits and contacts as stiff as MuJoCo's step keeps stable, nearer Bullet's hard ones than its default."""
    hinges = [joint for joint in spec.joints if joint.type == mujoco.mjtJoint.mjJNT_HINGE]
    for joint in hinges:
        joint.stiffness[:] = joint.damping[:] = joint.armature = 0.0
        joint.solref_limit = STIFF
    for geom in spec.geoms:
        geom.solref = STIFF
    geoms = spec.compile()  # the masses of the bodies' geoms
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO  # where a body states its own
    for name in BODIES:
        body, last = spec.body(name), spec.body(name).geoms[-1]
        body.explicitinertial = True
        body.mass = geoms.body(name).mass[0]
        capsule = last.type == mujoco.mjtGeom.mjGEOM_CAPSULE
        body.ipos = np.reshape(last.fromto, (2, 3)).mean(0) if capsule else np.zeros(3)
        body.inertia = BULLET_INERTIA[name.removeprefix("right_").removeprefix("left_")]
        body.iquat = [1.0, 0.0, 0.0, 0.0]
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    inertia = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, inertia)
    free = slice(0, 6)
    coupling = inertia[:, free] @ np.linalg.solve(inertia[free, free], inertia[free, :])
    for joint in hinges:
        dof = model.joint(joint.name).dofadr[0]
        joint.armature = (np.linalg.norm(joint.axis) - 1.0) * (inertia[dof, dof] - coupling[dof, dof])


def humanoid_model(cube, width, height):
    model = humanoid_spec(cube).compile()
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    return model


def quaternion(roll, pitch, yaw):
    """MuJoCo's (w, x, y, z) of Roboschool's Pose.set_rpy: yaw about z, then pitch about y, then roll about x."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    w = cy * cr * cp + sy * sr * sp
    x = cy * sr * cp - sy * cr * sp
    y = cy * cr * sp + sy * sr * cp
    z = sy * cr * cp - cy * sr * sp
    return np.array([w, x, y, z])


def roll_pitch_yaw(q):
    """Roboschool's Pose.rpy of a unit quaternion (w, x, y, z): the inverse of quaternion()."""
    w, x, y, z = q
    roll = np.arctan2(2 * (y * z + x * w), w * w - x * x - y * y + z * z)
    pitch = np.arcsin(np.clip(2 * (y * w - x * z), -1.0, 1.0))
    yaw = np.arctan2(2 * (x * y + z * w), w * w + x * x - y * y - z * z)
    return roll, pitch, yaw


class Forward:
    """RoboschoolHumanoid-v0, walk toward a target 1 km ahead, for N bodies of one model at once, each in its own MjData
    with its own random generator: each rule is one array operation over the bodies in `rows`. The methods follow
    Roboschool's RoboschoolForwardWalkersBase and RoboschoolHumanoid, in its order of calls; a single env is N = 1."""

    random_yaw = False  # Flagrun: start facing a random heading
    random_lean = False  # FlagrunHarder: half the starts lie on the front or the back
    cube = False  # FlagrunHarder: a cube is thrown at the body
    electricity_cost = ELECTRICITY_COST

    def __init__(self, model, datas):
        self.model, self.datas = model, datas
        self.rngs = [None] * len(datas)  # each body's generator, gymnasium's np_random, set by its env at a reset
        joints = [model.joint(name) for name, _ in MOTORS]
        self.qpos_index = np.array([joint.qposadr[0] for joint in joints])
        self.qvel_index = np.array([joint.dofadr[0] for joint in joints])
        low, high = np.array([joint.range for joint in joints]).T
        self.joint_mid = (low + high) / 2
        self.joint_half_range = (high - low) / 2
        # Roboschool's links: each body's at the centre of its last geom if that is a capsule, else at the body's origin
        # (the feet, the lower arms with their hands), and one at each joint.
        last_geom = model.body_geomadr + model.body_geomnum - 1
        self.torso = model.body("torso").id
        self.torso_geom = last_geom[self.torso]
        self.torso_offset = model.geom_pos[self.torso_geom].copy()  # from the torso's origin, in its frame
        parts = np.array([model.body(name).id for name in BODIES[1:]])
        capsule = model.geom_type[last_geom[parts]] == mujoco.mjtGeom.mjGEOM_CAPSULE
        self.part_geoms, self.part_origins = last_geom[parts[capsule]], parts[~capsule]
        self.joint_ids = np.array([joint.id for joint in joints])
        self.foot_geoms = [model.geom("right_foot").id, model.geom("left_foot").id]
        self.floor = model.geom("floor").id
        n = len(datas)  # what Roboschool keeps on its env, a row a body:
        self.frame, self.flags_reached, self.cubes_thrown, self.joints_at_limit = np.zeros((4, n), int)
        self.potential, self.walk_target_dist = np.zeros((2, n))
        self.feet_contact, self.target = np.zeros((2, n, 2))
        self.body_xyz, self.body_velocity = np.zeros((2, n, 3))
        self.joint_speeds = np.zeros((n, len(MOTORS)))
        self.flag_moved = np.zeros(n, bool)

    def reset(self, i):
        """Body i's start, with its generator: joints uniform in +-0.1 rad, at rest; returns its state."""
        rng, data = self.rngs[i], self.datas[i]
        mujoco.mj_resetData(self.model, data)  # the model's pose, at rest
        qpos = data.qpos
        qpos[self.qpos_index] = rng.uniform(-0.1, 0.1, len(MOTORS))
        z, pitch, yaw = 1.4, 0.0, 0.0  # the xml's pose: upright, facing x
        if self.random_yaw:
            yaw = rng.uniform(-3.14, 3.14)
            if self.random_lean and rng.integers(2) == 0:
                z, pitch = (0.45, np.pi / 2) if rng.integers(2) == 0 else (0.25, np.pi * 3 / 2)
        # Roboschool puts the torso's Bullet frame at (0, 0, z), and so 0.12 m higher than the xml's torso origin.
        qpos[3:7] = quaternion(0.0, pitch, yaw)
        mujoco.mju_rotVecQuat(offset := np.zeros(3), self.torso_offset, qpos[3:7])
        qpos[0:3] = np.array([0.0, 0.0, z]) - offset
        mujoco.mj_forward(self.model, data)
        self.frame[i] = 0
        self.feet_contact[i] = 0.0
        self.target[i] = [1e3, 0.0]
        self.cubes_thrown[i] = self.flags_reached[i] = 0
        self.task_reset(i)
        rows = np.array([i])
        state = self.calc_state(rows)[0]
        self.potential[i] = self.calc_potential(rows)[0]
        self.flags_reached[i] = 0  # a flag placed within reach of the start is not one reached
        return state

    def task_reset(self, i):
        self.datas[i].mocap_pos[0, :2] = self.target[i]

    def humanoid_state(self, rows):
        """The 44 numbers of the state of each body in `rows`; also keeps what the reward reads (joint speeds, joints
        at limit, the body's position, speed and angles, the distance to the target)."""
        datas = [self.datas[i] for i in rows]
        qpos = np.stack([data.qpos for data in datas])
        qvel = np.stack([data.qvel for data in datas])
        geoms = np.stack([data.geom_xpos for data in datas])
        positions = (qpos[:, self.qpos_index] - self.joint_mid) / self.joint_half_range
        self.joint_speeds[rows] = 0.1 * qvel[:, self.qvel_index]  # 10 rad/s is 1
        self.joints_at_limit[rows] = np.count_nonzero(np.abs(positions) > 0.99, axis=1)
        # The body's x, y: the mean of its parts' (29 links); its z: the torso's, "more informative than the mean".
        torso = geoms[:, self.torso_geom]
        origins = np.stack([data.xpos[self.part_origins] for data in datas])
        anchors = np.stack([data.xanchor[self.joint_ids] for data in datas])
        x, y = np.concatenate([geoms[:, self.part_geoms], origins, anchors], 1)[..., :2].mean(1).T
        self.body_xyz[rows] = np.stack([x, y, torso[:, 2]], 1)
        roll, pitch, yaw = roll_pitch_yaw(qpos[:, 3:7].T)
        # The torso frame's velocity: the free joint's (of the torso's origin), plus the spin's share at the offset.
        turn = np.stack([data.xmat[self.torso].reshape(3, 3) for data in datas])
        spin = (turn * qvel[:, None, 3:6]).sum(2)
        arm = torso - np.stack([data.xpos[self.torso] for data in datas])
        self.body_velocity[rows] = qvel[:, 0:3] + np.cross(spin, arm)
        to_target = self.target[rows] - self.body_xyz[rows, :2]
        self.walk_target_dist[rows] = np.linalg.norm(to_target, axis=1)
        angle_to_target = np.arctan2(to_target[:, 1], to_target[:, 0]) - yaw
        # The torso's velocity turned into the heading's frame; 0.3 brings typical speeds into [-1, 1].
        vx, vy, vz = self.body_velocity[rows].T
        velocity = [np.cos(yaw) * vx + np.sin(yaw) * vy, -np.sin(yaw) * vx + np.cos(yaw) * vy, vz]
        height = self.body_xyz[rows, 2] - INITIAL_Z
        more = [height, np.sin(angle_to_target), np.cos(angle_to_target), *(0.3 * np.array(velocity))]
        joints = np.stack([positions, self.joint_speeds[rows]], 2).reshape(len(rows), -1)  # joint by joint
        state = np.concatenate([np.stack([*more, roll, pitch], 1), joints, self.feet_contact[rows]], 1)
        return np.clip(state, -5.0, 5.0).astype(np.float32)

    def calc_state(self, rows):
        return self.humanoid_state(rows)

    def calc_potential(self, rows):
        """Progress is the change of this potential: a step toward the target of speed x dt earns speed (m/s)."""
        return -self.walk_target_dist[rows] / DT

    def alive_bonus(self, rows):
        # 2, not 1: the 17 joints' electricity cost from the policy's noise alone is large, and living must pay.
        return np.where(self.body_xyz[rows, 2] > 0.78, 2.0, -1.0)

    def feet_collision_cost(self, i):
        """Body i's feet's floor contacts (for the next step's state), and -1 for each that touches anything else."""
        pairs = self.datas[i].contact.geom.tolist()
        cost = 0.0
        for side, foot in enumerate(self.foot_geoms):
            touched = {one if two == foot else two for one, two in pairs if foot in (one, two)}
            self.feet_contact[i, side] = float(self.floor in touched)
            cost += FOOT_COLLISION_COST * bool(touched - {self.floor})
        return cost

    def step(self, actions):
        """Each body's step under its action: (states, rewards, terminations, the reward's terms and the rest)."""
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (len(self.datas), len(MOTORS)):  # no silent broadcast to 17 motors or to N bodies
            raise ValueError(f"Action dimension mismatch. Expected {(len(self.datas), len(MOTORS))}, found {a.shape}")
        ctrl, diverged = np.clip(a, -1.0, 1.0), np.zeros(len(self.datas), bool)  # torque: 0.41 x power x the ctrl
        for i, data in enumerate(self.datas):
            data.ctrl[:] = ctrl[i]
            resets = data.warning.number[UNSTABLE].tolist()
            mujoco.mj_step(self.model, data, nstep=FRAME_SKIP)
            diverged[i] = data.warning.number[UNSTABLE].tolist() != resets  # a count went up
            mujoco.mj_kinematics(self.model, data)  # the bodies' positions after the last physics step
        rows = np.arange(len(self.datas))
        self.flag_moved[:] = False
        state = self.calc_state(rows)
        alive = self.alive_bonus(rows)
        potential_old = self.potential.copy()
        self.potential = self.calc_potential(rows)
        terms = {
            "alive": alive,
            "progress": self.potential - potential_old,
            "electricity": self.electricity_cost * np.abs(a * self.joint_speeds).mean(1)
            + STALL_TORQUE_COST * np.square(a).mean(1),
            "joints_at_limit": JOINTS_AT_LIMIT_COST * self.joints_at_limit,
            "feet_collision": np.array([self.feet_collision_cost(i) for i in rows]),
        }
        # MuJoCo found the physics unstable and reset the body: a fall, with nothing paid for the jump
        terms = {name: np.where(diverged, -1.0 if name == "alive" else 0.0, value) for name, value in terms.items()}
        self.frame += 1
        terminated = (terms["alive"] < 0) | ~np.isfinite(state).all(1)
        info = {f"reward_{name}": value for name, value in terms.items()}
        info |= {"flags_reached": self.flags_reached.copy(), "flag_moved": self.flag_moved.copy()}
        info |= {"cubes_thrown": self.cubes_thrown.copy(), "distance_to_target": self.walk_target_dist.copy()}
        info |= {"torso_z": self.body_xyz[:, 2].copy()}
        return state, sum(terms.values()), terminated, info


class Flagrun(Forward):
    """RoboschoolHumanoidFlagrun-v0: run to a flag that moves when reached and every 200 steps."""

    random_yaw = True

    def __init__(self, model, datas):
        super().__init__(model, datas)
        self.flag_timeout = np.zeros(len(datas), int)

    def task_reset(self, i):
        self.flag_reposition(i)

    def flag_reposition(self, i):
        self.target[i] = self.rngs[i].uniform(-FLAG_HALF, FLAG_HALF)
        self.datas[i].mocap_pos[0, :2] = self.target[i]
        self.flag_timeout[i] = FLAG_TIMEOUT

    def calc_state(self, rows):
        self.flag_timeout[rows] -= 1
        state = self.humanoid_state(rows)
        moves = (self.walk_target_dist[rows] < 1) | (self.flag_timeout[rows] <= 0)
        if moves.any():
            moved = rows[moves]
            self.flags_reached[moved] += self.walk_target_dist[moved] < 1
            for i in moved:
                self.flag_reposition(i)
            self.flag_moved[moved] = True
            state[moves] = self.humanoid_state(moved)  # against the new flag
            self.potential[moved] = self.calc_potential(moved)  # so that the move pays no jump
        return state


class FlagrunHarder(Flagrun):
    """RoboschoolHumanoidFlagrunHarder-v0: Flagrun, starting half the time on the ground, pelted by a cube, paid for
    standing up and not for crawling."""

    random_lean = True
    cube = True
    electricity_cost = ELECTRICITY_COST / 4  # "don't care that much about electricity, just stand up!"

    def __init__(self, model, datas):
        super().__init__(model, datas)
        self.on_ground_frame_counter = np.zeros(len(datas), int)
        self.crawl_start_potential = np.full(len(datas), np.nan)  # nan: not crawling
        self.crawl_ignored_potential = np.zeros(len(datas))

    def task_reset(self, i):
        super().task_reset(i)
        self.on_ground_frame_counter[i] = 0
        self.crawl_start_potential[i] = np.nan
        self.crawl_ignored_potential[i] = 0.0

    def throw_cube(self, i):
        """The cube, from 4 m away at a random angle and 1 m up, at 20-30 m/s toward where the torso will be."""
        rng = self.rngs[i]
        angle = rng.uniform(-3.14, 3.14)
        attack_speed = rng.uniform(20.0, 30.0)
        target = self.body_xyz[i] + self.body_velocity[i] * (4.0 / attack_speed)
        start = target + np.array([4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.0])
        velocity = (target - start) * attack_speed / np.linalg.norm(target - start)
        velocity += rng.uniform(-1.0, 1.0, 3)
        self.datas[i].joint("cube").qpos[:] = [*start, 1.0, 0.0, 0.0, 0.0]
        self.datas[i].joint("cube").qvel[:] = [*velocity, 0.0, 0.0, 0.0]
        self.cubes_thrown[i] += 1

    def alive_bonus(self, rows):
        counter = self.on_ground_frame_counter
        for i in rows[(self.frame[rows] % 30 == 0) & (self.frame[rows] > 100) & (counter[rows] == 0)]:
            self.throw_cube(i)
        down = self.body_xyz[rows, 2] < 0.8
        counter[rows] += np.where(down, 1, np.where(counter[rows] > 0, -1, 0))
        # The episode ends if the body cannot get up within 170 steps.
        return np.where(counter[rows] < 170, self.potential_leak(rows), -1.0)

    def potential_leak(self, rows):
        """1 on the ground, up to 2 standing: the alive bonus, seen as what a potential of 100 x this leaks each step
        with gamma 0.99 ((1 - 0.99) x 200 = 2)."""
        return np.clip(self.body_xyz[rows, 2], 0.0, 0.8) / 0.8 + 1.0

    def calc_potential(self, rows):
        flag_running_progress = super().calc_potential(rows)
        # Crawling: the progress made below 0.8 m is ignored, now and after getting up.
        down = self.body_xyz[rows, 2] < 0.8
        start = self.crawl_start_potential[rows]
        start = np.where(down & np.isnan(start), flag_running_progress - self.crawl_ignored_potential[rows], start)
        ignored = np.where(down, flag_running_progress - start, self.crawl_ignored_potential[rows])
        flag_running_progress = np.where(down, start, flag_running_progress - ignored)
        self.crawl_start_potential[rows] = np.where(down, start, np.nan)
        self.crawl_ignored_potential[rows] = ignored
        # Standing up raises the potential by 100: that is why the body would get up.
        return flag_running_progress + self.potential_leak(rows) * 100


class HumanoidEnv(MujocoEnv, gym.utils.EzPickle):
    """One of the tasks as a gymnasium env: its rules for one body (N = 1), with gymnasium's MuJoCo rendering."""

    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"], "render_fps": round(1 / DT)}
    rules = Forward

    def __init__(self, render_mode=None, width=480, height=480, camera_name=None, camera_id=None):
        camera_name = "track" if camera_name is None and camera_id is None else camera_name
        space = gym.spaces.Box(-5.0, 5.0, (44,), np.float32)
        super().__init__("humanoid.xml", FRAME_SKIP, space, render_mode, width, height, camera_id, camera_name)
        gym.utils.EzPickle.__init__(self, render_mode, width, height, camera_name, camera_id)  # pickles as arguments
        self.bodies = self.rules(self.model, [self.data])

    def _initialize_simulation(self):
        model = humanoid_model(self.rules.cube, self.width, self.height)
        return model, mujoco.MjData(model)

    def reset_model(self):
        self.bodies.rngs[0] = self.np_random
        return self.bodies.reset(0)

    def step(self, action):
        if np.shape(action) != (len(MOTORS),):  # as gymnasium's Humanoid-v5 refuses it
            raise ValueError(f"Action dimension mismatch. Expected {(len(MOTORS),)}, found {np.shape(action)}")
        state, reward, terminated, info = self.bodies.step(np.asarray(action)[None])
        if self.render_mode == "human":
            self.render()
        return state[0], float(reward[0]), bool(terminated[0]), False, {key: v[0].item() for key, v in info.items()}

    def render(self):
        """The film's camera follows the body from behind and to the side, and looks past it toward the target."""
        ground = self.data.geom_xpos[self.bodies.torso_geom] * [1, 1, 0]  # below the torso
        ahead = np.append(self.bodies.target[0], 0.0) - ground
        ahead /= max(np.linalg.norm(ahead), 1e-6)
        camera = self.model.camera("track")
        side = np.cross(ahead, [0.0, 0.0, 1.0])  # to the right, so that the body does not hide the flag
        camera.pos = ground - CAMERA_BACK * ahead + CAMERA_SIDE * side + [0, 0, CAMERA_UP]
        look = ground + CAMERA_LOOK * ahead - camera.pos
        look /= np.linalg.norm(look)
        right = np.cross(look, [0.0, 0.0, 1.0]) / np.linalg.norm(look[:2])
        mujoco.mju_mat2Quat(camera.quat, np.stack([right, np.cross(-look, right), -look], 1).ravel())
        mujoco.mj_kinematics(self.model, self.data)  # the flag where calc_state() last moved it
        mujoco.mj_camlight(self.model, self.data)  # and the camera where it now is
        return super().render()


class HumanoidVectorEnv(gym.vector.VectorEnv):
    """N of one task's envs in one: the rules computed once over N bodies of one model, each in its own MjData, with
    the same episodes as N single envs of the same seeds. As gymnasium's SyncVectorEnv in its SAME_STEP mode: the step
    that ends an episode returns the next one's first state, and the last one in infos["final_obs"]."""

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}
    rules = Forward

    def __init__(self, num_envs, max_episode_steps=1000):
        model = humanoid_model(self.rules.cube, 1, 1)
        self.bodies = self.rules(model, [mujoco.MjData(model) for _ in range(num_envs)])
        self.num_envs, self.max_episode_steps = num_envs, max_episode_steps
        self.elapsed = np.zeros(num_envs, int)
        self.single_observation_space = gym.spaces.Box(-5.0, 5.0, (44,), np.float32)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (len(MOTORS),), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed=None, options=None):
        seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else seed or [None] * self.num_envs
        for i, one in enumerate(seeds):
            if one is not None or self.bodies.rngs[i] is None:
                self.bodies.rngs[i] = gym.utils.seeding.np_random(one)[0]
        self.elapsed[:] = 0
        return np.stack([self.bodies.reset(i) for i in range(self.num_envs)]), {}

    def step(self, actions):
        state, reward, terminated, info = self.bodies.step(actions)
        self.elapsed += 1
        truncated = self.elapsed >= self.max_episode_steps
        ended = terminated | truncated
        # The infos as SyncVectorEnv merges them: an env reset in this step has its reset's info (none) and its last
        # step's in final_info; a mask _key says which envs have each key.
        infos = {}
        if ended.any():
            infos["final_obs"] = np.full(self.num_envs, None, object)
            last = {key: np.where(ended, value, 0).astype(value.dtype) for key, value in info.items()}
            infos["final_info"] = last | {f"_{key}": ended.copy() for key in info}
            infos |= {"_final_obs": ended.copy(), "_final_info": ended.copy()}
            for i in np.flatnonzero(ended):
                infos["final_obs"][i] = state[i].copy()
                state[i] = self.bodies.reset(i)
            self.elapsed[ended] = 0
        if not ended.all():
            infos |= {key: np.where(ended, 0, value).astype(value.dtype) for key, value in info.items()}
            infos |= {f"_{key}": ~ended for key in info}
        return state, reward, terminated, truncated, infos


# The tasks, each as a gymnasium env (N = 1) and as its own vector env (gym.make_vec), registered under one id.
for _rules in (Forward, Flagrun, FlagrunHarder):
    _name = f"Humanoid{_rules.__name__}"
    globals()[_name] = type(_name, (HumanoidEnv,), {"rules": _rules, "__doc__": _rules.__doc__})
    globals()[f"{_name}Vector"] = type(f"{_name}Vector", (HumanoidVectorEnv,), {"rules": _rules})
    if f"{_name}-v0" not in gym.registry:
        _entry = f"{__name__}:{_name}"
        gym.register(f"{_name}-v0", entry_point=_entry, vector_entry_point=f"{_entry}Vector", max_episode_steps=1000)
