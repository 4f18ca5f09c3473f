"""The peer at an equal budget: Stable-Baselines3's PPO on an Atari game with the RL Zoo's Atari
hyperparameters, run by benchmarks/run.py beside ppo_atari.py and read back the same way.

    python benchmarks/sb3_atari.py --env-id PongNoFrameskip-v4 --total-timesteps 1000000 --run-dir runs/sb3-pong
    python benchmarks/sb3_atari.py --resume runs/sb3-pong/checkpoint.pt

The hyperparameters are rl-baselines3-zoo's hyperparams/ppo.yml, `atari`: AtariWrapper (30 no-ops,
4-frame skip with max-pooling, a lost life ends an episode, FIRE at reset, 84x84 gray, rewards
clipped to their sign) and a 4-frame stack; 8 envs x 128 steps, 4 epochs of minibatches of 256,
lr 2.5e-4 and clip range 0.1, both annealed linearly to 0, vf_coef 0.5 (on SB3's unhalved squared
error), ent_coef 0.01; the rest at SB3's defaults (gamma 0.99, GAE lambda 0.95, max_grad_norm 0.5).

It writes what ppo_atari.py writes, so that run.py and report.py treat both alike: TensorBoard
scalars charts/episodic_return (the raw score of a whole game, from SB3's Monitor, which sits below
the Atari wrappers) and charts/episodic_length (in agent steps), and a checkpoint.pt with the step,
beside SB3's own model file. Ctrl-C or SIGTERM saves both and exits 130; --resume continues the run.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

from common import sb3_main

FRAME_SKIP = 4
N_ENVS, N_STEPS = 8, 128
ROLLOUT = N_ENVS * N_STEPS  # agent steps per rollout
# What run.py records of a run beside the packages every run records.
RESULTS_PACKAGES = ("stable-baselines3",)


@dataclass
class Args:
    env_id: str = "BreakoutNoFrameskip-v4"  # a gymnasium Atari id without frame skip (the Atari wrappers skip frames)
    seed: int = 1  # SB3 seeds env i with seed + i
    total_timesteps: int = 1_000_000  # agent steps over all 8 envs
    torch_threads: int = 1  # torch CPU threads
    save_every: int = 50  # save the model and checkpoint.pt every this many rollouts (and at the end, and on a stop)
    run_dir: str | None = (
        None  # where the TensorBoard logs, the model and checkpoint.pt go (default: runs/sb3_atari__{env_id}__{seed})
    )
    resume: str | None = None  # continue the run of this checkpoint.pt, with its own arguments


def check_args(args):
    """A ValueError with a one-line reason for bad input, before anything heavy loads."""
    for name in ("total_timesteps", "torch_threads", "save_every"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.resume is not None and not os.path.isfile(args.resume):
        raise ValueError(f"checkpoint {args.resume!r} does not exist")
    if "NoFrameskip" not in args.env_id:
        raise ValueError(f"{args.env_id} is not a NoFrameskip Atari id: SB3's Atari wrappers skip frames themselves")


def make_model(args, run_dir):
    import ale_py
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack

    gym.register_envs(ale_py)
    envs = VecFrameStack(make_atari_env(args.env_id, n_envs=N_ENVS, seed=args.seed), n_stack=4)
    model_path = os.path.join(run_dir, "sb3_model.zip")
    if os.path.exists(model_path):  # a resumed run: the weights, the optimizer and the step count
        return PPO.load(model_path, env=envs, device="cpu"), model_path
    model = PPO(
        "CnnPolicy",
        envs,
        n_steps=N_STEPS,
        n_epochs=4,
        batch_size=256,
        learning_rate=lambda progress_remaining: 2.5e-4 * progress_remaining,
        clip_range=lambda progress_remaining: 0.1 * progress_remaining,
        vf_coef=0.5,
        ent_coef=0.01,
        device="cpu",
        seed=args.seed,
        verbose=0,
    )
    return model, model_path


def main():
    sb3_main(
        "sb3_atari.py",
        Args,
        check_args,
        make_model,
        lambda args: f"runs/sb3_atari__{args.env_id}__{args.seed}",
        lambda args: args.save_every * ROLLOUT,
        lambda n: math.ceil(n / FRAME_SKIP),
    )


if __name__ == "__main__":
    main()
