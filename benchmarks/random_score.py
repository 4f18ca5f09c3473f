"""The score of the uniformly random policy, measured with the same protocol as our runs.

    python benchmarks/random_score.py --env-id BreakoutNoFrameskip-v4 --episodes 100
    python benchmarks/random_score.py --env-id Hopper-v5 --episodes 100

Atari games are played as ppo_atari.py's evaluation plays them (ale-py's vector env as that script
makes it: no sticky actions, up to 30 no-ops, FIRE on reset, whole games over all lives, raw
score); MuJoCo tasks through gymnasium with their time limits. Writes
benchmarks/results/random/<env>.csv (a header of '# ' lines, then one row per episode) and prints
the mean return, the random policy's score. The paper normalizes Table 1 with this score.
"""

import argparse
import csv
import importlib.util
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from collect import machine, versions  # noqa: E402


def atari_returns(env_id, episodes, seed):
    spec = importlib.util.spec_from_file_location("ppo_atari", ROOT / "ppo_atari.py")
    ppo_atari = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = ppo_atari
    spec.loader.exec_module(ppo_atari)
    envs = ppo_atari.make_envs(ppo_atari.Args(env_id=env_id), num_envs=1, training=False)
    rng = np.random.default_rng(seed)
    rows = []
    for episode in range(episodes):
        envs.reset(seed=seed + episode)
        total, length, done = 0.0, 0, False
        while not done:
            _, reward, term, trunc, _ = envs.step(rng.integers(0, envs.single_action_space.n, size=1))
            total, length, done = total + float(reward[0]), length + 1, bool(term[0] or trunc[0])
        rows.append((episode, total, length))
    envs.close()
    return rows


def mujoco_returns(env_id, episodes, seed):
    import gymnasium as gym

    env = gym.make(env_id)
    env.action_space.seed(seed)
    rows = []
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        total, length, done = 0.0, 0, False
        while not done:
            _, reward, term, trunc, _ = env.step(env.action_space.sample())
            total, length, done = total + float(reward), length + 1, term or trunc
        rows.append((episode, total, length))
    env.close()
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--env-id", required=True)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if args.episodes <= 0:
        parser.error("--episodes must be positive")
    is_atari = "NoFrameskip" in args.env_id or args.env_id.startswith("ALE/")
    rows = (atari_returns if is_atari else mujoco_returns)(args.env_id, args.episodes, args.seed)
    out = ROOT / "benchmarks" / "results" / "random" / f"{args.env_id.replace('/', '-')}.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "w", newline="") as f:
        f.write(f"# command: python benchmarks/random_score.py --env-id {args.env_id} --episodes {args.episodes} --seed {args.seed}\n")
        f.write(f"# versions: {versions()}\n# machine: {machine()}\n")
        writer = csv.writer(f)
        writer.writerow(["episode", "episodic_return", "episodic_length"])
        writer.writerows(rows)
    returns = [r for _, r, _ in rows]
    print(f"{args.env_id}: random policy {statistics.mean(returns):.2f} ± {statistics.stdev(returns) if len(returns) > 1 else 0:.2f} over {len(returns)} episodes; wrote {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
