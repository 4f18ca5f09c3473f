"""What the roboschool suite's trained policies do, in units a reader knows: flags reached per episode, speed toward the
flag, and, for FlagrunHarder, falls, the cube's knock-downs, and the share of times and the steps it takes to get up.

    python benchmarks/roboschool_measures.py                            # each run of the suite at its budget
    python benchmarks/roboschool_measures.py --suite roboschool-body    # Roboschool's body, at 100M and at 50M
    python benchmarks/roboschool_measures.py --suite roboschool-bullet  # the body measured against Bullet
    python benchmarks/roboschool_measures.py --total-timesteps 10027008 # the 10M pilots and seeds
    python benchmarks/roboschool_measures.py --checkpoint runs/x/checkpoint.pt   # any run's, printed only
    python benchmarks/roboschool_measures.py --total-timesteps 10027008 --film  # and film each run

With --film, each run's film goes to results/<suite folder>/video/<run>.mp4, with a frame of it (.png): the first of
the measured episodes that shows what the task asks (a fall it gets up from, for FlagrunHarder; a flag reached, else a
flag moved, for Flagrun; else its first episode), filmed from the start to its end, the frame 30 steps after that
event (the middle of the episode if none), with the flag and the cube in sight of a camera that follows the body.
A checkpoint that run.py kept midway (below) is filmed as well, into video/<label>/.

Each run's checkpoint plays --episodes episodes (seeds 1, 2, ...) with its deterministic policy (the Gaussian's mean,
as --eval-checkpoint plays it), and one row an episode goes to results/<suite folder>/measures/<run>.csv, which the
suite's report reads. A checkpoint that run.py kept midway through a long run (checkpoint_50M.pt, the first saved at
or past the mark) plays the same episodes into measures/50M/<run>.csv. The body is down while its torso is below
0.8 m, FlagrunHarder's rule for "on the ground"; a fall is a step from up to down, a knock-down a fall within 30 steps
of a cube's throw, and a get-up a step from down to up.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT))
from common import load_script  # noqa: E402
from roboschool_humanoid import DT  # noqa: E402  (seconds a step)
from run import make_grid  # noqa: E402

DOWN = 0.8  # m: FlagrunHarder's "on the ground"
FIELDS = "seed return length flags speed_to_flag started_down falls knockdowns cubes getups getup_steps step".split()


def policy(checkpoint_path):
    """(env_id, act(obs), step): the checkpoint's env, its deterministic policy on raw observations, and its step."""
    import gymnasium as gym
    import torch

    script = load_script("ppo_continuous.py")
    checkpoint, train_args = script.load_checkpoint(str(checkpoint_path), script.Args())
    env = gym.make(train_args.env_id)
    agent = script.Agent(env.observation_space.shape[0], env.action_space.shape[0], norm_obs=train_args.norm_obs)
    agent.load_state_dict(checkpoint["agent"])
    env.close()

    def act(obs):
        with torch.inference_mode():
            action = agent.actor_mean(torch.as_tensor(agent.normalize_obs(obs[None])))[0].numpy()
        return np.clip(action, -1.0, 1.0)

    return train_args.env_id, act, checkpoint["global_step"]


def play(checkpoint_path, episodes):
    """One dict of FIELDS an episode of the checkpoint's deterministic policy, on its own env, seeds 1..episodes."""
    import gymnasium as gym

    env_id, act, checkpoint_step = policy(checkpoint_path)
    return play_policy(gym.make(env_id), act, episodes, checkpoint_step)


def play_policy(env, act, episodes, checkpoint_step=""):
    """One dict of FIELDS an episode of act(state) on `env` (a task's env, or one with the same infos), seeds
    1..episodes; the env is closed at the end."""
    rows = []
    for seed in range(1, episodes + 1):
        obs, _ = env.reset(seed=seed)
        row = dict.fromkeys(FIELDS, 0)
        row["seed"], row["step"] = seed, checkpoint_step
        row["started_down"] = int(obs[0] + 0.8 < DOWN)  # the state's first number: the torso's height above 0.8 m
        down_since = 0 if row["started_down"] else None
        last_throw = -1000
        speeds = []
        distance = None
        getup_steps = []
        cubes = 0
        for step in range(1, 10**6):
            obs, reward, terminated, truncated, info = env.step(act(obs))
            row["return"] += float(reward)
            if distance is not None and not info["flag_moved"]:
                speeds.append((distance - info["distance_to_target"]) / DT)
            distance = info["distance_to_target"]
            if info["cubes_thrown"] > cubes:
                cubes = info["cubes_thrown"]
                last_throw = step
            down = info["torso_z"] < DOWN
            if down and down_since is None:
                down_since = step
                row["falls"] += 1
                row["knockdowns"] += step - last_throw <= 30
            elif not down and down_since is not None:
                getup_steps.append(step - down_since)
                down_since = None
            if terminated or truncated:
                break
        row.update(length=step, flags=info["flags_reached"], cubes=cubes, getups=len(getup_steps))
        row["speed_to_flag"] = float(np.mean(speeds)) if speeds else 0.0
        row["getup_steps"] = float(np.mean(getup_steps)) if getup_steps else ""
        rows.append(row)
    env.close()
    return rows


def film_pixel(env, point):
    """Where the film's camera sees a world point, in pixels (u right, v down), by its pinhole projection; None when the
    point is behind the camera."""
    camera = env.data.camera("track")
    seen = camera.xmat.reshape(3, 3).T @ (point - camera.xpos)  # the camera looks along its -z, its y up
    if seen[2] >= 0:
        return None
    focal = env.height / 2 / np.tan(np.radians(env.model.camera("track").fovy[0]) / 2)
    return np.array([env.width / 2 + focal * seen[0] / -seen[2], env.height / 2 - focal * seen[1] / -seen[2]])


def in_frame(env, point):
    pixel = film_pixel(env, point)
    return pixel is not None and 0 <= pixel[0] < env.width and 0 <= pixel[1] < env.height


def frame_measures(env):
    """What a frame just rendered shows, by projection (occlusion aside): the share of the frame's height between the
    head's top and the lowest foot's bottom; whether the flag is within 8 m and in frame (its foot and its ball);
    whether a cube is in flight and in frame."""
    data = env.data
    head = film_pixel(env, data.geom("head").xpos + [0, 0, 0.09])
    feet = film_pixel(
        env, min(data.geom("right_foot").xpos, data.geom("left_foot").xpos, key=lambda p: p[2]) - [0, 0, 0.075]
    )
    span = abs(head[1] - feet[1]) / env.height if head is not None and feet is not None else 0.0
    flag = data.mocap_pos[0]
    near = np.linalg.norm(flag[:2] - env.bodies.body_xyz[0, :2]) < 8.0
    flag_seen = near and in_frame(env, flag) and in_frame(env, flag + [0, 0, 1.5])
    flying = env.rules.cube and data.body("cube").xpos[2] > 0.1
    return dict(
        body_span=span,
        flag_near=near,
        flag_seen=flag_seen,
        cube_flying=flying,
        cube_seen=flying and in_frame(env, data.body("cube").xpos),
    )


FILM_FIELDS = "frames body_span_median body_span_p5 flag_near flag_seen cube_flying cube_seen".split()


def film(checkpoint_path, rows, video):
    """Film the first measured episode that shows the task's event (see the docstring); returns its seed. Beside the
    video, <video>.csv says what its frames show (frame_measures: the body's span, the flag and the cube in sight)."""
    import os

    import gymnasium as gym
    import imageio.v3 as iio

    os.environ.setdefault("MUJOCO_GL", "egl")
    env_id, act, _ = policy(checkpoint_path)
    harder = env_id.endswith("HumanoidFlagrunHarder-v0")
    shows = [r for r in rows if (r["getups"] > r["started_down"] if harder else r["flags"] > 0)]
    seed = (shows or rows)[0]["seed"]
    env = gym.make(env_id, render_mode="rgb_array", width=512, height=384)
    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    shown = [frame_measures(env.unwrapped)]
    event = None
    down = obs[0] + 0.8 < DOWN  # the state's first number: the torso's height above 0.8 m
    fell = False
    for step in range(1, 10**6):
        obs, _, terminated, truncated, info = env.step(act(obs))
        frames.append(env.render())
        shown.append(frame_measures(env.unwrapped))
        if harder:  # the first get-up after a fall (not from a start on the ground)
            fell = fell or (not down and info["torso_z"] < DOWN)
            if fell and down and info["torso_z"] >= DOWN and event is None:
                event = step
            down = info["torso_z"] < DOWN
        elif event is None and (info["flags_reached"] or (info["flag_moved"] and not shows)):
            event = step
        if terminated or truncated:
            break
    env.close()
    video.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(video, np.stack(frames), fps=30, codec="libx264")
    at = min(len(frames) - 1, event + 30) if event is not None else len(frames) // 2
    iio.imwrite(video.with_suffix(".png"), frames[at])
    spans = [f["body_span"] for f in shown]
    counts = {key: sum(f[key] for f in shown) for key in ("flag_near", "flag_seen", "cube_flying", "cube_seen")}
    with open(video.with_suffix(".csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, FILM_FIELDS)
        writer.writeheader()
        row = dict(
            frames=len(shown), body_span_median=f"{np.median(spans):.3f}", body_span_p5=f"{np.percentile(spans, 5):.3f}"
        )
        writer.writerow(row | counts)
    return seed


def write(path, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def summary(rows):
    """One line: the means over episodes of what a reader can picture."""
    mean = {key: np.mean([float(r[key]) for r in rows if r[key] != ""] or [np.nan]) for key in FIELDS[1:]}
    downs = sum(r["falls"] + r["started_down"] for r in rows)
    share = f"{sum(r['getups'] for r in rows)}/{downs}" if downs else "-"
    steps_up = f"{mean['getup_steps']:.0f}" if np.isfinite(mean["getup_steps"]) else "-"
    return (
        f"return {mean['return']:.0f}, {mean['length']:.0f} steps, {mean['flags']:.1f} flags, "
        f"{mean['speed_to_flag']:.2f} m/s toward the flag, {mean['falls']:.1f} falls "
        f"({mean['knockdowns']:.1f} knock-downs), got up {share} times, in {steps_up} steps"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--suite", default="roboschool", help="roboschool, roboschool-body or roboschool-bullet")
    parser.add_argument("--total-timesteps", type=int, help="the suite's budget whose runs to measure (its default)")
    parser.add_argument("--checkpoint", type=Path, help="measure this checkpoint only, and print it")
    parser.add_argument("--episodes", type=int, default=30, help="deterministic episodes per run (env seeds 1, 2, ...)")
    parser.add_argument("--film", action="store_true", help="also film each run (results/<folder>/video/)")
    args = parser.parse_args()
    if args.episodes <= 0 or (args.total_timesteps is not None and args.total_timesteps <= 0):
        parser.error("--episodes and --total-timesteps must be positive")
    if args.checkpoint:
        print(summary(play(args.checkpoint, args.episodes)))
        return
    for job in make_grid(args.suite, total_timesteps=args.total_timesteps):
        if job.checkpoint.exists() and job.csv.exists():
            # Those run.py kept midway go to measures/<label>/ and video/<label>/, the last checkpoint to the folders.
            kept = [
                (path, path.stem.removeprefix("checkpoint_")) for path in sorted(job.run_dir.glob("checkpoint_*.pt"))
            ]
            for checkpoint, label in [*kept, (job.checkpoint, "")]:
                rows = play(checkpoint, args.episodes)
                write(job.results_dir / "measures" / label / f"{job.name}.csv", rows)
                print(f"{job.name}{' at ' + label if label else ''}: {summary(rows)}", flush=True)
                if args.film:
                    video = job.results_dir / "video" / label / f"{job.name}.mp4"
                    print(f"  filmed episode seed {film(checkpoint, rows, video)}: {video}", flush=True)


if __name__ == "__main__":
    main()
