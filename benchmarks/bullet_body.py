"""Roboschool's humanoid on Bullet: the reference that roboschool_humanoid.py's MuJoCo body is measured against.

Roboschool (openai/roboschool at 911f7cd, the release the PPO paper ran) stepped humanoid_symmetric.xml in its own build
of Bullet, which no longer installs. PyBullet 3.2.7 ships the same file, byte for byte, and the same importer's
successor, so it stands in for that build here. This module loads the body as Roboschool's physics-bullet.cpp did:
- gravity 9.8 m/s^2; a step of 4 physics steps of 0.0165 / 4 s (one call with 4 substeps); 5 solver iterations; a
  contact ERP of 0.9;
- humanoid_symmetric.xml with self-collision, except between a link and any of its ancestors
  (URDF_USE_SELF_COLLISION | URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS);
- Roboschool's ground_plane.xml (a plane of friction 0.8) and its cube.urdf (0.1 m, 0.6 kg), loaded the same way;
- each motor's torque 0.41 x its power x the action clipped to [-1, 1], the importer's velocity motors off.

A `State` is what both engines can be put into and read back: the torso's Bullet frame (the centre of its last geom,
uwaist), its orientation, its velocity and spin in the world frame, and the 17 joints' positions and speeds.
`BulletBody.observe` computes Roboschool's 44 numbers from Bullet's links as Roboschool's calc_state did, so that
tests/test_bullet_body.py can check that roboschool_humanoid.py reads the same state the same way. The tasks
themselves stay on MuJoCo; `set_mujoco` and `get_mujoco` put a `State` into, and read it out of, one of its bodies.
bullet_distances.py and zoo_agent.py measure the two engines with it.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from roboschool_humanoid import DT, FRAME_SKIP, MOTORS, POWER, roll_pitch_yaw  # noqa: E402

GRAVITY = 9.8
SOLVER_ITERATIONS = 5
CONTACT_ERP = 0.9
# Roboschool's floor and its thrown cube, as its mujoco_assets/ground_plane.xml and models_household/cube.urdf are.
GROUND_PLANE = """<mujoco model="ground_plane"><worldbody>
<geom conaffinity="1" condim="3" name="floor" friction="0.8 0.1 0.1" pos="0 0 0" type="plane"/>
</worldbody></mujoco>"""
CUBE = """<?xml version="1.0"?><robot name="cube"><link name="cube">
<collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision>
<inertial><mass value="0.6"/><inertia ixx="0.001" iyy="0.001" izz="0.001"/></inertial>
</link></robot>"""
ZOO = Path(__file__).resolve().parent / "zoo" / "RoboschoolHumanoidFlagrunHarder_v0_2017may.npz"


class State(NamedTuple):
    """A body's state in either engine: positions in m, angles in rad, the quaternion as (w, x, y, z)."""

    pos: np.ndarray  # the torso's Bullet frame: uwaist's centre
    quat: np.ndarray  # the torso's orientation
    vel: np.ndarray  # the velocity of that point, world frame
    spin: np.ndarray  # the torso's angular velocity, world frame
    qpos: np.ndarray  # the 17 joints in MOTORS' order
    qvel: np.ndarray


def zoo_agent():
    """Roboschool's agent for FlagrunHarder: a 44-256-128-17 ReLU network on the raw state (see zoo/README.md)."""
    w = np.load(ZOO)

    def act(state):
        x = np.maximum(state @ w["weights_dense1_w"] + w["weights_dense1_b"], 0.0)
        x = np.maximum(x @ w["weights_dense2_w"] + w["weights_dense2_b"], 0.0)
        return x @ w["weights_final_w"] + w["weights_final_b"]

    return act


class BulletBody:
    """One humanoid, the floor and (with `cube`) the cube in a PyBullet world of their own, as Roboschool set them."""

    def __init__(self, cube=True):
        import pybullet
        import pybullet_data
        from pybullet_utils.bullet_client import BulletClient

        self.pb = pybullet
        self.p = p = BulletClient(pybullet.DIRECT)
        p.setGravity(0, 0, -GRAVITY)
        p.setDefaultContactERP(CONTACT_ERP)
        p.setPhysicsEngineParameter(fixedTimeStep=DT, numSubSteps=FRAME_SKIP, numSolverIterations=SOLVER_ITERATIONS)
        flags = pybullet.URDF_USE_SELF_COLLISION | pybullet.URDF_USE_SELF_COLLISION_EXCLUDE_ALL_PARENTS
        with tempfile.TemporaryDirectory() as folder:
            for name, text in (("ground_plane.xml", GROUND_PLANE), ("cube.urdf", CUBE)):
                Path(folder, name).write_text(text)
            (self.floor,) = p.loadMJCF(os.path.join(folder, "ground_plane.xml"), flags=flags)
            self.cube = p.loadURDF(os.path.join(folder, "cube.urdf"), [-1.5, 0, 0.05], flags=flags) if cube else None
        xml = os.path.join(pybullet_data.getDataPath(), "mjcf", "humanoid_symmetric.xml")  # Roboschool's, byte for byte
        (self.body,) = p.loadMJCF(xml, flags=flags)
        links = {p.getJointInfo(self.body, j)[12].decode(): j for j in range(p.getNumJoints(self.body))}
        joints = {p.getJointInfo(self.body, j)[1].decode(): j for j in range(p.getNumJoints(self.body))}
        self.joints = [joints[name] for name, _ in MOTORS]
        self.links = list(links.values())  # Roboschool's parts: every link but the base (12 bodies, 17 joints')
        self.feet = [links["right_foot"], links["left_foot"]]
        limits = np.array([p.getJointInfo(self.body, j)[8:10] for j in self.joints])
        self.joint_mid, self.joint_half_range = limits.mean(1), (limits[:, 1] - limits[:, 0]) / 2
        self.torque = POWER * np.array([power for _, power in MOTORS])
        for j in range(p.getNumJoints(self.body)):  # the importer's velocity motors off: torque control only
            p.setJointMotorControl2(self.body, j, pybullet.VELOCITY_CONTROL, force=0)

    def set_state(self, state):
        w, x, y, z = state.quat
        self.p.resetBasePositionAndOrientation(self.body, state.pos, [x, y, z, w])
        self.p.resetBaseVelocity(self.body, state.vel, state.spin)
        for j, q, v in zip(self.joints, state.qpos, state.qvel, strict=True):
            self.p.resetJointState(self.body, j, q, v)

    def get_state(self):
        pos, (x, y, z, w) = self.p.getBasePositionAndOrientation(self.body)
        vel, spin = self.p.getBaseVelocity(self.body)
        joints = self.p.getJointStates(self.body, self.joints)
        qpos, qvel = np.array([joint[:2] for joint in joints]).T
        return State(np.array(pos), np.array([w, x, y, z]), np.array(vel), np.array(spin), qpos, qvel)

    def step(self, action):
        """One step of 4 physics steps under `action`, then each foot's contact with the floor (Roboschool's state
        reads them at the next step)."""
        torques = self.torque * np.clip(action, -1.0, 1.0)
        self.p.setJointMotorControlArray(self.body, self.joints, self.pb.TORQUE_CONTROL, forces=torques.tolist())
        self.p.stepSimulation()
        return self.feet_contact()

    def feet_contact(self):
        touching = [{contact[2] for contact in self.p.getContactPoints(self.body, -1, foot)} for foot in self.feet]
        return np.array([float(self.floor in bodies) for bodies in touching])

    def observe(self, target, feet_contact):
        """Roboschool's 44 numbers (calc_state), read from Bullet's links, toward `target` (x, y)."""
        p = self.p
        state = self.get_state()
        parts = np.array([link[0] for link in p.getLinkStates(self.body, self.links)])
        x, y = parts[:, :2].mean(0)
        z = state.pos[2]
        # Roboschool's Pose.rpy: at a pitch of +-90 degrees (the starts lying down) it splits the turn between roll and
        # yaw its own way, where PyBullet's getEulerFromQuaternion splits it another
        roll, pitch, yaw = roll_pitch_yaw(state.quat)
        angle_to_target = np.arctan2(target[1] - y, target[0] - x) - yaw
        turn = np.array([[np.cos(yaw), np.sin(yaw), 0.0], [-np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        vx, vy, vz = turn @ state.vel
        more = [z - 0.8, np.sin(angle_to_target), np.cos(angle_to_target), 0.3 * vx, 0.3 * vy, 0.3 * vz, roll, pitch]
        positions = (state.qpos - self.joint_mid) / self.joint_half_range
        joints = np.stack([positions, 0.1 * state.qvel], 1).ravel()
        return np.clip(np.concatenate([more, joints, feet_contact]), -5.0, 5.0)


def set_mujoco(bodies, i, state):
    """Put body i of roboschool_humanoid's rules (`bodies`, a Forward) into `state`; the rest of its MjData stays."""
    import mujoco

    model, data = bodies.model, bodies.datas[i]
    data.qpos[3:7] = state.quat
    turn = np.zeros(9)
    mujoco.mju_quat2Mat(turn, state.quat)
    offset = turn.reshape(3, 3) @ bodies.torso_offset  # from the torso's origin to its Bullet frame, world frame
    data.qpos[0:3] = state.pos - offset
    data.qvel[0:3] = state.vel - np.cross(state.spin, offset)  # the free joint moves the origin
    data.qvel[3:6] = turn.reshape(3, 3).T @ state.spin  # and spins in the body's frame
    data.qpos[bodies.qpos_index] = state.qpos
    data.qvel[bodies.qvel_index] = state.qvel
    mujoco.mj_forward(model, data)


def get_mujoco(bodies, i):
    data = bodies.datas[i]
    turn = data.xmat[bodies.torso].reshape(3, 3)
    offset = turn @ bodies.torso_offset
    spin = turn @ data.qvel[3:6]
    return State(
        data.qpos[0:3] + offset,
        data.qpos[3:7].copy(),
        data.qvel[0:3] + np.cross(spin, offset),
        spin,
        data.qpos[bodies.qpos_index].copy(),
        data.qvel[bodies.qvel_index].copy(),
    )
