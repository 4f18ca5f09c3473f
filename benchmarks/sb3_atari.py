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
import signal
import sys
from dataclasses import asdict, dataclass

FRAME_SKIP = 4
RUNTIME_FIELDS = ("torch_threads", "save_every", "resume")


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
    envs = VecFrameStack(make_atari_env(args.env_id, n_envs=8, seed=args.seed), n_stack=4)
    model_path = os.path.join(run_dir, "sb3_model.zip")
    if os.path.exists(model_path):  # a resumed run: the weights, the optimizer and the step count
        return PPO.load(model_path, env=envs, device="cpu"), model_path
    model = PPO(
        "CnnPolicy",
        envs,
        n_steps=128,
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
    import tyro

    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        print(f"sb3_atari.py: error: {e}", file=sys.stderr)
        sys.exit(2)
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from torch.utils.tensorboard import SummaryWriter

    if args.resume is not None:
        saved = torch.load(args.resume, map_location="cpu", weights_only=True)
        args = Args(
            **{
                **saved["args"],
                **{k: getattr(args, k) for k in RUNTIME_FIELDS},
                "run_dir": os.path.dirname(os.path.abspath(args.resume)),
            }
        )
    run_dir = args.run_dir or f"runs/sb3_atari__{args.env_id}__{args.seed}"
    os.makedirs(run_dir, exist_ok=True)
    torch.set_num_threads(args.torch_threads)
    model, model_path = make_model(args, run_dir)
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    writer = SummaryWriter(run_dir, purge_step=model.num_timesteps + 1 if args.resume else None)
    stop = []
    previous = {
        sig: signal.signal(sig, lambda signum, frame: stop.append(signum)) for sig in (signal.SIGINT, signal.SIGTERM)
    }

    def save():
        model.save(model_path)
        writer.flush()
        torch.save(
            {"format": "sb3-checkpoint-v1", "args": asdict(args), "global_step": model.num_timesteps},
            f"{checkpoint_path}.tmp",
        )
        os.replace(f"{checkpoint_path}.tmp", checkpoint_path)

    class Log(BaseCallback):
        rollouts = 0

        def _on_step(self):
            for info in self.locals["infos"]:
                if "episode" in info:  # a whole game ended (Monitor is below the episodic-life wrapper)
                    writer.add_scalar("charts/episodic_return", info["episode"]["r"], self.num_timesteps)
                    writer.add_scalar(
                        "charts/episodic_length", math.ceil(info["episode"]["l"] / FRAME_SKIP), self.num_timesteps
                    )
            return not stop

        def _on_rollout_end(self):
            Log.rollouts += 1
            if Log.rollouts % args.save_every == 0:
                save()
            print(f"step {self.num_timesteps:,}/{args.total_timesteps:,}", flush=True)

    model.learn(args.total_timesteps - model.num_timesteps, callback=Log(), reset_num_timesteps=False)
    save()
    writer.close()
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    if stop:
        print(f"stopped: saved step {model.num_timesteps:,}; continue with --resume {checkpoint_path}")
        sys.exit(130)
    print(f"saved {checkpoint_path}")


if __name__ == "__main__":
    main()
