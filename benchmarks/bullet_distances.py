"""How far roboschool_humanoid.py's MuJoCo body moves from Bullet's under the same actions, setting by setting.

Bullet's body is bullet_body.py's; each setting is one that might bring the two closer. The table goes to
results/bullet/distances.md.

    python benchmarks/bullet_distances.py               # every setting (a few minutes), the table regenerated
    python benchmarks/bullet_distances.py --settings module no-damping   # some of them, printed only

Both engines start from the same states and get the same actions; after 1, 5, 20 and 60 steps (1 s) the table gives
the rms distance of the 17 joints' angles (rad) and the distance between the torsos' Bullet frames (m), each the mean
over the trajectories. The starts (3 seeds each, joints uniform in +-0.1 rad at rest, as an episode starts): standing,
lying on the front, lying on the back, and mid-stride, the states of Roboschool's own agent on Bullet after 60, 120 and
180 steps toward a target ahead. The actions: that agent's own, recorded on Bullet from the same start (played to
MuJoCo as a recording); uniform random in [-1, 1]; and bang-bang, each motor at +-1 at random. A trajectory on which
MuJoCo reports an unstable step is counted, and left out of the means.

Bullet does not repeat itself exactly from one world to the next, nor from one process to the next: the row "Bullet
itself, in worlds of its own" is how far it moves from itself within one run, and from one run of this script to the
next a row moves by up to about 0.02 rad at step 20. A setting earns its place in the module where it brings the
joints nearer after 5 and 20 steps by more than that; after 60 steps Bullet has parted from itself by about 0.2 rad,
and the two engines by chaos as much as by their physics. Bullet's own rows (its damping of every link's motion taken
out, its clamp on joint speeds lifted) say how much those parts of Bullet move it; the row that adds that damping to
MuJoCo, each physics step, says how much of it MuJoCo would recover.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bullet_body as bb  # noqa: E402
from bullet_body import ROOT, State  # noqa: E402

import results  # noqa: E402

sys.path.insert(0, str(ROOT))
import roboschool_humanoid as rh  # noqa: E402

STEPS = (1, 5, 20, 60)
SEEDS = (1, 2, 3)
OUT = ROOT / "benchmarks" / "results" / "bullet" / "distances.md"
BODY = ["roboschool_humanoid.py", "benchmarks/bullet_body.py", "benchmarks/bullet_distances.py"]  # what the table is of
PACKAGES = ("numpy", "gymnasium", "mujoco", "pybullet")


def hinges(spec):
    import mujoco

    return [joint for joint in spec.joints if joint.type == mujoco.mjtJoint.mjJNT_HINGE]


def damping(value):
    def change(spec):
        for joint in hinges(spec):
            joint.damping[:] = value

    return change


def unit_axes(spec):
    """MuJoCo's unit axes, as if Bullet had normalized them: no armature, each motor's full gear."""
    for joint in hinges(spec):
        joint.armature = 0.0
        spec.actuator(joint.name).gear[0] *= np.linalg.norm(joint.axis)


def whole_inertia_armature(spec):
    """The shoulders' and elbows' armature from the whole inertia about the axis, the floating torso's share kept."""
    import mujoco

    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    inertia = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, inertia)
    for joint in hinges(spec):
        dof = model.joint(joint.name).dofadr[0]
        joint.armature = (np.linalg.norm(joint.axis) - 1.0) * (inertia[dof, dof] - model.dof_armature[dof])


def gymnasium_armature(spec):
    import gymnasium.envs.mujoco
    import mujoco

    path = Path(gymnasium.envs.mujoco.__file__).parent / "assets" / "humanoid.xml"
    theirs = mujoco.MjSpec.from_file(str(path))
    for joint in hinges(spec):
        joint.armature = theirs.joint(joint.name).armature


def geoms_inertia(spec):
    """MuJoCo's inertia of the geoms, where the module states Bullet's."""
    import mujoco

    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE


def limits(time_constant):
    def change(spec):
        for joint in hinges(spec):
            joint.solref_limit = [time_constant, 1.0]

    return change


def friction(value):
    """Every geom's friction (the cube's aside): Bullet multiplies the two surfaces' 0.8 into 0.64, MuJoCo takes the
    larger of the two."""

    def change(spec):
        for geom in spec.geoms:
            geom.friction[0] = value
        for geom in spec.body("cube").geoms:
            geom.friction[0] = 1.0

    return change


def contacts(time_constant):
    def change(spec):
        for geom in spec.geoms:
            geom.solref = [time_constant, 1.0]

    return change


def integrator(name):
    def change(spec):
        import mujoco

        spec.option.integrator = getattr(mujoco.mjtIntegrator, f"mjINT_{name}")

    return change


EARLIER = [damping(0.5), unit_axes, gymnasium_armature, geoms_inertia, limits(0.02), contacts(0.02)]
# Each setting: its changes to the module's spec, and its physics steps a step (the module's: 4). The module's body
# first, then each of its choices taken back one at a time, then the earlier body, then what else might help.
SETTINGS = {
    "the module's body": ([], 4),
    "with a damper of 0.5 on every joint": ([damping(0.5)], 4),
    "with a damper of 0.1 on every joint": ([damping(0.1)], 4),
    "with unit axes (no armature, full gears)": ([unit_axes], 4),
    "with the armature of the whole inertia about the axis": ([whole_inertia_armature], 4),
    "with unit axes and gymnasium's armature": ([unit_axes, gymnasium_armature], 4),
    "with the geoms' inertia": ([geoms_inertia], 4),
    "with MuJoCo's default limits (0.02 s)": ([limits(0.02)], 4),
    "with MuJoCo's default contacts (0.02 s)": ([contacts(0.02)], 4),
    "the earlier body (damper 0.5, unit axes, gymnasium's armature, the geoms' inertia, limits and contacts 0.02 s)": (
        EARLIER,
        4,
    ),
    "and 8 physics steps a step": ([], 8),
    "and limits and contacts of 0.005 s, 8 physics steps": ([limits(0.005), contacts(0.005)], 8),
    "and friction 0.64": ([friction(0.64)], 4),
    "and Euler's integrator": ([integrator("EULER")], 4),
    "and RK4": ([integrator("RK4")], 4),
}


class MuJoCoBody:
    """The module's rules over one body of a changed model, stepped `substeps` physics steps a step."""

    def __init__(self, changes, substeps):
        import mujoco

        spec = rh.humanoid_spec(cube=True)
        for change in changes:
            change(spec)
        spec.option.timestep = rh.DT / substeps
        self.model = spec.compile()
        self.bodies = rh.Forward(self.model, [mujoco.MjData(self.model)])
        self.substeps = substeps

    def set_state(self, state):
        import mujoco

        mujoco.mj_resetData(self.model, self.bodies.datas[0])
        bb.set_mujoco(self.bodies, 0, state)

    def get_state(self):
        return bb.get_mujoco(self.bodies, 0)

    def step(self, action):
        """A step under `action`; False if MuJoCo found it unstable."""
        import mujoco

        data = self.bodies.datas[0]
        data.ctrl[:] = np.clip(action, -1.0, 1.0)
        before = data.warning.number[rh.UNSTABLE].tolist()
        mujoco.mj_step(self.model, data, nstep=self.substeps)
        return data.warning.number[rh.UNSTABLE].tolist() == before


class DampedBody(MuJoCoBody):
    """The module's body with btMultiBody's own damping: each physics step, every link is pushed back by its mass x
    its velocity x (0.04 + 0.04 |velocity|), and turned back by its inertia x its spin x (0.04 + 0.04 |spin|)."""

    damping = 0.04  # btMultiBody's m_linearDamping and m_angularDamping

    def step(self, action):
        import mujoco

        model, data = self.model, self.bodies.datas[0]
        data.ctrl[:] = np.clip(action, -1.0, 1.0)
        bodies = [model.body(name).id for name in rh.BODIES]
        velocity = np.zeros(6)  # spin, then velocity, at the centre of mass, in the world frame
        before = data.warning.number[rh.UNSTABLE].tolist()
        for _ in range(self.substeps):
            for b in bodies:
                mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, b, velocity, 0)
                spin, linear = velocity[:3], velocity[3:]
                turn = data.ximat[b].reshape(3, 3)
                inertia = turn @ np.diag(model.body_inertia[b]) @ turn.T
                data.xfrc_applied[b, :3] = -model.body_mass[b] * linear * self.damping * (1 + np.linalg.norm(linear))
                data.xfrc_applied[b, 3:] = -inertia @ spin * self.damping * (1 + np.linalg.norm(spin))
            mujoco.mj_step(model, data)
        return data.warning.number[rh.UNSTABLE].tolist() == before


def start(kind, seed):
    """A start as an episode's: joints uniform in +-0.1 rad, at rest, the torso standing or lying."""
    rng = np.random.default_rng(seed)
    qpos = rng.uniform(-0.1, 0.1, len(rh.MOTORS))
    z, pitch = {"standing": (1.4, 0.0), "front": (0.45, np.pi / 2), "back": (0.25, np.pi * 3 / 2)}[kind]
    quat = rh.quaternion(0.0, pitch, rng.uniform(-np.pi, np.pi))
    zero = np.zeros(3)
    return State(np.array([0.0, 0.0, z]), quat, zero, zero, qpos, np.zeros(len(rh.MOTORS)))


def agent_run(state, steps, act, target):
    """Roboschool's agent on Bullet from `state`: its states and actions, step by step."""
    body = bb.BulletBody()
    body.set_state(state)
    feet = np.zeros(2)
    states, actions = [state], []
    for _ in range(steps):
        action = act(body.observe(target, feet))
        feet = body.step(action)
        states.append(body.get_state())
        actions.append(action)
    body.p.disconnect()
    return states, actions


def trajectories(act):
    """(start, actions) pairs: every start with every kind of actions, 60 steps each."""
    pairs = []
    for seed in SEEDS:
        starts = [start(kind, seed) for kind in ("standing", "front", "back")]
        states, _ = agent_run(start("standing", seed), 60 * seed, act, target=(1e3, 0.0))
        starts.append(states[-1])
        rng = np.random.default_rng(100 + seed)
        for state in starts:
            target = state.pos[:2] + 1e3 * np.array([1.0, 0.0])
            _, agent = agent_run(state, STEPS[-1], act, target)
            random = rng.uniform(-1.0, 1.0, (STEPS[-1], len(rh.MOTORS)))
            bang = rng.choice([-1.0, 1.0], (STEPS[-1], len(rh.MOTORS)))
            pairs += [(state, "agent", agent), (state, "random", random), (state, "bang-bang", bang)]
    return pairs


def play(engine, state, actions):
    """The states of `engine` at each of STEPS from `state` under `actions`, and whether every step was stable. A
    Bullet world is made anew for each trajectory: one that is reset keeps its contacts' warm start from the last."""
    engine = engine() if callable(engine) else engine
    engine.set_state(state)
    states, stable = [], True
    for step, action in enumerate(actions, 1):
        stable &= engine.step(action) is not False  # Bullet's returns its feet
        if step in STEPS:
            states.append(engine.get_state())
    if isinstance(engine, bb.BulletBody):
        engine.p.disconnect()
    return states, stable


def distances(engine, reference, pairs):
    """Mean joints' rms (rad) and torso distance (m) from Bullet's at each of STEPS, over the stable trajectories, and
    the number of unstable ones."""
    joints, torso, unstable = [], [], 0
    for (state, _, actions), theirs in zip(pairs, reference, strict=True):
        ours, stable = play(engine, state, actions)
        if stable:
            joints.append([np.sqrt(np.mean((one.qpos - two.qpos) ** 2)) for one, two in zip(ours, theirs, strict=True)])
            torso.append([np.linalg.norm(one.pos - two.pos) for one, two in zip(ours, theirs, strict=True)])
        else:
            unstable += 1
    return np.mean(joints, 0), np.mean(torso, 0), unstable


def bullet_changed(**dynamics):
    """Bullet itself with btMultiBody's damping or its velocity clamp changed: how much they move Bullet."""

    def make():
        body = bb.BulletBody()
        for link in range(-1, body.p.getNumJoints(body.body)):
            body.p.changeDynamics(body.body, link, **dynamics)
        return body

    return make


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), metavar="NAME", help="these only, printed")
    args = parser.parse_args()
    pairs = trajectories(bb.zoo_agent())
    reference = [play(bb.BulletBody, state, actions)[0] for state, _, actions in pairs]
    rows = []
    names = args.settings or list(SETTINGS)
    engines = {name: MuJoCoBody(*SETTINGS[name]) for name in names}
    if not args.settings:
        engines["and btMultiBody's damping of every link, each physics step"] = DampedBody([], 4)
    if not args.settings:  # Bullet against itself: as it is, with its own damping off, or its velocity clamp lifted
        engines["Bullet itself, in worlds of its own"] = bullet_changed()
        engines["Bullet, no btMultiBody damping"] = bullet_changed(linearDamping=0.0, angularDamping=0.0)
        engines["Bullet, no velocity clamp"] = bullet_changed(maxJointVelocity=1000.0)
    for name, engine in engines.items():
        joints, torso, unstable = distances(engine, reference, pairs)
        cells = [f"{j:.3f} / {t:.3f}" for j, t in zip(joints, torso, strict=True)]
        rows.append(f"| {name} | " + " | ".join(cells) + f" | {unstable} of {len(pairs)} |")
        print(rows[-1], flush=True)
    if not args.settings:
        OUT.parent.mkdir(parents=True, exist_ok=True)
        header = "| setting | " + " | ".join(f"step {s}: joints (rad) / torso (m)" for s in STEPS) + " | unstable |"
        rule = "|" + "---|" * (len(STEPS) + 2)
        about = [f"- Seeds {', '.join(map(str, SEEDS))} of each start; {len(pairs)} trajectories of {STEPS[-1]} steps."]
        about += [f"- Commit {results.commit(BODY, '+')}; {results.versions(PACKAGES)}; {results.machine()}."]
        about += ["- Command: `python benchmarks/bullet_distances.py`"]
        OUT.write_text("\n".join([__doc__.split("\n")[0], "", header, rule, *rows, "", *about]) + "\n")


if __name__ == "__main__":
    main()
