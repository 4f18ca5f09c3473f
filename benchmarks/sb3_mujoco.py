"""The peers of the paper's Figure 3: Stable-Baselines3's A2C and sb3-contrib's TRPO on a MuJoCo task, with the
RL Zoo's tuned hyperparameters, run by benchmarks/run.py beside ppo_continuous.py and read back the same way.

    python benchmarks/sb3_mujoco.py --algo trpo --env-id Hopper-v5 --total-timesteps 1000000 --run-dir runs/trpo-hopper
    python benchmarks/sb3_mujoco.py --resume runs/trpo-hopper/checkpoint.pt

The hyperparameters are read from the installed rl_zoo3 package's own files, hyperparams/a2c.yml and trpo.yml, as
the Zoo reads them: the task's entry, else the file's `default` entry (SB3's defaults). The Zoo tuned its MuJoCo
entries on gym's -v4 tasks; a -v5 task takes its -v4 entry, since -v5 is the same task with fixes to the model
files. `normalize: true` wraps the envs in VecNormalize (observations and rewards, with the entry's gamma), a
learning rate `lin_X` is annealed linearly from X to 0, and `n_timesteps` gives way to --total-timesteps.
`hyperparameters()` returns what a run uses and where it came from, for the CSV's header and the report.

It writes what ppo_continuous.py writes, so that run.py and report.py treat both alike: TensorBoard scalars
charts/episodic_return (the env's own undiscounted return, from SB3's Monitor, below VecNormalize) and
charts/episodic_length, and a checkpoint.pt with the step, beside SB3's model file and the VecNormalize
statistics. Ctrl-C or SIGTERM saves them all and exits 130; --resume continues the run.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from common import sb3_main

ALGOS = ("a2c", "trpo")
# What run.py records of a run beside the packages every run records.
RESULTS_PACKAGES = ("stable-baselines3", "sb3-contrib", "rl_zoo3")


@dataclass
class Args:
    algo: str = "trpo"  # a2c (Stable-Baselines3) or trpo (sb3-contrib)
    env_id: str = "Hopper-v5"  # a gymnasium MuJoCo id
    seed: int = 1  # SB3 seeds env i with seed + i
    total_timesteps: int = 1_000_000  # env steps over all envs
    torch_threads: int = 1  # torch CPU threads
    save_every: int = (
        50_000  # save the model and checkpoint.pt about every this many steps (and at the end, and on a stop)
    )
    run_dir: str | None = (
        None  # where the logs, the model and checkpoint.pt go (default: runs/sb3_{algo}__{env_id}__{seed})
    )
    resume: str | None = None  # continue the run of this checkpoint.pt, with its own arguments


def check_args(args):
    """A ValueError with a one-line reason for bad input, before anything heavy loads."""
    if args.algo not in ALGOS:
        raise ValueError(f"--algo must be one of {', '.join(ALGOS)}, got {args.algo!r}")
    for name in ("total_timesteps", "torch_threads", "save_every"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.resume is not None and not os.path.isfile(args.resume):
        raise ValueError(f"checkpoint {args.resume!r} does not exist")


def hyperparameters(algo, env_id):
    """The RL Zoo's entry for (algo, env_id) as the Zoo would train with it, and a line saying which entry it is."""
    from importlib.resources import files

    import yaml

    table = yaml.safe_load((files("rl_zoo3") / "hyperparams" / f"{algo}.yml").read_text())
    name, version = env_id.rsplit("-v", 1)
    candidates = [env_id] + ([f"{name}-v4"] if version == "5" else [])
    key = next((c for c in candidates if c in table), "default")
    source = f"rl_zoo3 hyperparams/{algo}.yml, entry {key}" + (
        " (the Zoo has no entry for this task: SB3's defaults)" if key == "default" else ""
    )
    return dict(table[key]), source


def results_header(flags, env_id):
    """The header lines run.py adds to a run's CSV: which RL Zoo entry the run's --algo took on env_id."""
    algo = flags[flags.index("--algo") + 1] if "--algo" in flags else Args.algo
    return [("hyperparameters", hyperparameters(algo, env_id)[1])]


def make_model(args, run_dir):
    import gymnasium as gym  # noqa: F401  (registers the MuJoCo envs)
    from sb3_contrib import TRPO
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize
    from torch import nn  # noqa: F401  (the Zoo's policy_kwargs strings name nn)

    params, source = hyperparameters(args.algo, args.env_id)
    print(f"{args.algo} on {args.env_id}: {source}", flush=True)
    params.pop("n_timesteps", None)
    policy = params.pop("policy")
    envs = make_vec_env(args.env_id, n_envs=params.pop("n_envs", 1), seed=args.seed)
    normalize = params.pop("normalize", False)
    if isinstance(normalize, str):
        normalize = eval(normalize)
    if normalize:
        kwargs = normalize if isinstance(normalize, dict) else {}
        kwargs = {**kwargs, **({"gamma": params["gamma"]} if "gamma" in params else {})}
        stats = os.path.join(run_dir, "vecnormalize.pkl")
        envs = VecNormalize.load(stats, envs) if os.path.exists(stats) else VecNormalize(envs, **kwargs)
    if isinstance(params.get("learning_rate"), str):  # "lin_X": from X down to 0 over the run
        start = float(params["learning_rate"].split("_")[1])
        params["learning_rate"] = lambda progress_remaining: start * progress_remaining
    if isinstance(params.get("policy_kwargs"), str):
        params["policy_kwargs"] = eval(params["policy_kwargs"])
    algo = {"a2c": A2C, "trpo": TRPO}[args.algo]
    model_path = os.path.join(run_dir, "sb3_model.zip")
    if os.path.exists(model_path):  # a resumed run: the weights, the optimizer and the step count
        return algo.load(model_path, env=envs, device="cpu"), model_path
    return algo(policy, envs, device="cpu", seed=args.seed, verbose=0, **params), model_path


def main():
    sb3_main(
        "sb3_mujoco.py",
        Args,
        check_args,
        make_model,
        lambda args: f"runs/sb3_{args.algo}__{args.env_id}__{args.seed}",
        lambda args: args.save_every,
    )


if __name__ == "__main__":
    main()
