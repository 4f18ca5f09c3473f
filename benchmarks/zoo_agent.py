"""Roboschool's own FlagrunHarder agent on both engines: the acceptance of roboschool_humanoid.py's body.

Roboschool shipped agents trained on its own Bullet body (agent_zoo/, see zoo/README.md). On a body that moves as
Bullet's did, its FlagrunHarder agent should get up as it did there. It plays --episodes episodes (seeds 1, 2, ...)
of HumanoidFlagrunHarder-v0 on MuJoCo, and the same task's rules on Bullet (bullet_body.py), which draw the same
starts, flags and throws from the same seeds; both are measured by roboschool_measures.py's play loop (steps, flags,
speed toward the flag, falls, knock-downs, get-ups). One row an episode goes to results/bullet/zoo_<engine>.csv, and
the table to results/bullet/zoo.md.

    python benchmarks/zoo_agent.py                  # 50 episodes on each engine, the report regenerated
    python benchmarks/zoo_agent.py --report         # the report only, from the CSVs
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bullet_body as bb  # noqa: E402
import roboschool_measures as measures  # noqa: E402
from bullet_body import ROOT, State  # noqa: E402

import results  # noqa: E402

sys.path.insert(0, str(ROOT))
import roboschool_humanoid as rh  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bullet"
ENGINES = {"mujoco": "this project's MuJoCo body", "bullet": "PyBullet 3.2.7"}
BODY = ["roboschool_humanoid.py", "benchmarks/bullet_body.py", "benchmarks/zoo_agent.py"]  # what the measures are of
PACKAGES = ("numpy", "gymnasium", "mujoco", "pybullet")


class BulletFlagrunHarder:
    """HumanoidFlagrunHarder-v0's episode on Bullet: the module's starts, flags, throws and end, drawn in its order from
    gymnasium's generator of the same seed, and the infos that roboschool_measures.play_policy reads. It keeps no
    reward: the acceptance measures what the body does, not its score."""

    def __init__(self):
        self.body = bb.BulletBody(cube=True)

    def reset(self, seed):
        import gymnasium as gym

        self.rng = rng = gym.utils.seeding.np_random(seed)[0]
        qpos = rng.uniform(-0.1, 0.1, len(rh.MOTORS))
        z, pitch, yaw = 1.4, 0.0, rng.uniform(-3.14, 3.14)
        if rng.integers(2) == 0:
            z, pitch = (0.45, np.pi / 2) if rng.integers(2) == 0 else (0.25, np.pi * 3 / 2)
        zero = np.zeros(3)
        self.body.set_state(State(np.array([0, 0, z]), rh.quaternion(0, pitch, yaw), zero, zero, qpos, qpos * 0))
        p = self.body.p
        p.resetBasePositionAndOrientation(self.body.cube, [-1.5, 0.0, 0.05], [0, 0, 0, 1])
        p.resetBaseVelocity(self.body.cube, [0, 0, 0], [0, 0, 0])
        self.frame = self.flags = self.cubes = self.on_ground = self.elapsed = 0
        self.feet = np.zeros(2)
        self.move_flag()
        state, _ = self.observe()
        self.flags = 0  # a flag placed within reach of the start is not one reached
        return state, {}

    def move_flag(self):
        self.target = self.rng.uniform(-rh.FLAG_HALF, rh.FLAG_HALF)
        self.flag_timeout = rh.FLAG_TIMEOUT

    def where(self):
        """The body's x, y (the mean of its 29 links), its torso's height, the distance to the flag."""
        p = self.body.p
        parts = np.array([link[0] for link in p.getLinkStates(self.body.body, self.body.links)])
        xyz = np.append(parts[:, :2].mean(0), p.getBasePositionAndOrientation(self.body.body)[0][2])
        return xyz, np.linalg.norm(self.target - xyz[:2])

    def observe(self):
        self.flag_timeout -= 1
        xyz, distance = self.where()
        moved = distance < 1 or self.flag_timeout <= 0
        if moved:
            self.flags += distance < 1
            self.move_flag()
        return self.body.observe(self.target, self.feet), moved

    def throw_cube(self, xyz):
        """As FlagrunHarder.throw_cube: from 4 m at a random angle and 1 m up, at 20-30 m/s, where the torso will be."""
        angle = self.rng.uniform(-3.14, 3.14)
        attack_speed = self.rng.uniform(20.0, 30.0)
        velocity = np.array(self.body.p.getBaseVelocity(self.body.body)[0])
        target = xyz + velocity * (4.0 / attack_speed)
        start = target + np.array([4.0 * np.cos(angle), 4.0 * np.sin(angle), 1.0])
        aim = (target - start) * attack_speed / np.linalg.norm(target - start) + self.rng.uniform(-1.0, 1.0, 3)
        self.body.p.resetBasePositionAndOrientation(self.body.cube, start, [0, 0, 0, 1])
        self.body.p.resetBaseVelocity(self.body.cube, aim, [0, 0, 0])
        self.cubes += 1

    def step(self, action):
        contacts = self.body.step(action)
        state, moved = self.observe()
        self.feet = contacts  # the next state reads them, as Roboschool's did
        xyz, distance = self.where()
        if self.frame % 30 == 0 and self.frame > 100 and self.on_ground == 0:
            self.throw_cube(xyz)
        down = xyz[2] < 0.8
        self.on_ground += 1 if down else -1 if self.on_ground > 0 else 0
        self.frame += 1
        self.elapsed += 1
        info = dict(flags_reached=self.flags, flag_moved=moved, cubes_thrown=self.cubes)
        info |= dict(distance_to_target=distance, torso_z=xyz[2])
        return state, np.nan, self.on_ground >= 170, self.elapsed >= 1000, info

    def close(self):
        self.body.p.disconnect()


def make(engine):
    import gymnasium as gym

    return BulletFlagrunHarder() if engine == "bullet" else gym.make("roboschool_humanoid:HumanoidFlagrunHarder-v0")


def report():
    """results/bullet/zoo.md from the CSVs: each engine's means over its episodes."""
    lines = [__doc__.split("\n")[0], ""]
    lines += ["| engine | episodes | steps an episode | flags an episode | speed toward the flag (m/s) | falls "]
    lines[-1] += "(knock-downs) an episode | up again, of the times down |"
    lines += ["|---|---|---|---|---|---|---|"]
    about = []
    for engine, label in ENGINES.items():
        path = OUT / f"zoo_{engine}.csv"
        if not path.exists():
            continue
        with open(path) as f:
            made = f.readline().removeprefix("# ").strip()  # the first line says what made the file
            rows = list(csv.DictReader(f))
        about.append(f"- {label}: {made}.")
        mean = {key: np.mean([float(r[key]) for r in rows]) for key in ("length", "flags", "speed_to_flag", "falls")}
        knocks = np.mean([float(r["knockdowns"]) for r in rows])
        downs = sum(int(r["falls"]) + int(r["started_down"]) for r in rows)
        ups = sum(int(r["getups"]) for r in rows)
        cells = [label, len(rows), f"{mean['length']:.0f}", f"{mean['flags']:.2f}", f"{mean['speed_to_flag']:.2f}"]
        cells += [f"{mean['falls']:.2f} ({knocks:.2f})", f"{ups} of {downs} ({100 * ups / max(downs, 1):.0f}%)"]
        lines.append("| " + " | ".join(map(str, cells)) + " |")
    lines += ["", "The agent acts deterministically; an episode ends at 1,000 steps or after 170 steps on the ground."]
    lines += ["Seeds 1, 2, ... on each engine; a time down is a fall or a start on the ground. Bullet does not repeat"]
    lines[-1] += " itself from one process to the next, so its row changes from one run of the command to another."
    lines += ["", *about]
    lines += ["- Command: `python benchmarks/zoo_agent.py`"]
    (OUT / "zoo.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=50, help="episodes on each engine (seeds 1, 2, ...)")
    parser.add_argument("--engines", nargs="+", choices=list(ENGINES), default=list(ENGINES))
    parser.add_argument("--report", action="store_true", help="only regenerate zoo.md from the CSVs")
    args = parser.parse_args()
    if args.episodes <= 0:
        parser.error("--episodes must be positive")
    if not args.report:
        for engine in args.engines:
            rows = measures.play_policy(make(engine), bb.zoo_agent(), args.episodes)
            made = f"commit {results.commit(BODY, '+')}; {results.versions(PACKAGES)}; {results.machine()}"
            OUT.mkdir(parents=True, exist_ok=True)
            with open(OUT / f"zoo_{engine}.csv", "w", newline="") as f:
                f.write(f"# {made}\n")
                writer = csv.DictWriter(f, measures.FIELDS)
                writer.writeheader()
                writer.writerows(rows)
            print(f"{engine}: {measures.summary(rows)}", flush=True)
    report()


if __name__ == "__main__":
    main()
