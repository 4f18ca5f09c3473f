"""Steps per second of our scripts beside their peers, measured side by side in one run.

    pip install -r benchmarks/requirements.txt
    python benchmarks/throughput.py                 # all three scripts: MuJoCo, then Atari, about 10 minutes
    python benchmarks/throughput.py --suite mujoco  # ppo_continuous.py and ppo_kl_penalty.py on Hopper, about 5 minutes
    python benchmarks/throughput.py --suite atari   # ppo_atari.py on Breakout, about 5 minutes
    python benchmarks/throughput.py --suite humanoid  # ppo_continuous.py with the paper's Table 4, about 20 minutes
    python benchmarks/throughput.py --suite roboschool  # roboschool_humanoid.py's envs alone beside Humanoid-v5's

Every measurement runs in a fresh process, one at a time, and the cases are repeated in
alternation (ours, peer, env, ours, peer, env, ...) so that a slow spell of the machine hits all of
them alike. Each suite's table reports the median steps/s of each case and the ratios, and
replaces that suite's section of benchmarks/results/throughput.md, together with the command,
commit, versions and machine; the other suite's section is kept as it was measured.

What is timed, for each case, is the learning itself on identical settings, in its steady state:
from the end of the first iteration (rollout + update) to the end of the last, so that neither
imports, model construction nor torch.compile's compilation count. The time to the end of the
first iteration is reported beside it: for `--compile`, less the eager script's, that is the
compilation's cost.
- ours: `train(args)` of the script, rollout + update + TensorBoard logging + checkpointing, eager
  and with `--compile`, with the torch threads that the script's `main()` sets (`--torch-threads`); the
  iteration ends are the wall times of its `charts/SPS` events. A case that starts with `torchrun --nproc-per-node P`
  is the same `train(args)` in P processes of one run, timed by rank 0, whose steps count every rank's;
- the peers: `model.learn()` of Stable-Baselines3's PPO with the same hyperparameters, network and
  normalization (VecNormalize), once with torch's default threads and once with 1 thread; the
  iteration ends are its rollout ends;
- env: the environment alone, stepped with random actions: the ceiling for any agent.
A suite of envs alone (roboschool) has no script of ours and no peer: its cases are envs, each stepped alone with
random actions as `env` is, and compared with the first.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.append(str(ROOT))  # for env ids of a module beside the scripts (roboschool_humanoid:...)
from common import load_script, replace_between  # noqa: E402
from results import commit, machine, versions  # noqa: E402
from suites import ROBOSCHOOL, TABLE4, TABLE4_128  # noqa: E402

# A suite: its env, our scripts, and their peers.
# Each run also measures the env alone.
SUITES = {
    "mujoco": {
        "env_id": "Hopper-v5",
        "steps": 10240,  # 5 rollouts of 2048
        "ours": ["ppo_continuous.py", "ppo_continuous.py --compile", "ppo_kl_penalty.py"],
        "peers": ["sb3_ppo_mujoco", "sb3_ppo_mujoco_1thread"],
        "settings": "1 env, T=2048, K=10 epochs, minibatch 64, 64x64 tanh MLPs",
    },
    "atari": {
        "env_id": "BreakoutNoFrameskip-v4",
        "steps": 6144,  # 6 rollouts of 8 x 128
        "ours": [
            "ppo_atari.py",
            "ppo_atari.py --compile",
            "torchrun --nproc-per-node 2 ppo_atari.py --torch-threads 1",
        ],
        "peers": ["sb3_ppo_atari"],
        "settings": "8 envs, T=128, K=3 epochs, minibatch 256, Nature CNN, lr and clip annealed",
    },
    # The paper's §6.3 (Table 4): many actors, whose policy steps are batched. Every case of ours adds "flags"; the
    # 128-actor case keeps the batch of 16,384 steps with T=128. env: the 32 envs of the same vector env, alone.
    "humanoid": {
        "env_id": "Humanoid-v5",
        "steps": 49152,  # 3 rollouts of 32 x 512
        "flags": shlex.join(TABLE4),  # the humanoid suite's flags, benchmarks/suites.py
        "ours": [
            "ppo_continuous.py",
            "ppo_continuous.py --compile",
            "ppo_continuous.py --num-envs 128 --num-steps 128",
            "torchrun --nproc-per-node 2 ppo_continuous.py",
        ],
        "peers": ["sb3_ppo_humanoid", "sb3_ppo_humanoid_1thread"],
        "settings": "Table 4: 32 envs, T=512, K=15 epochs, minibatch 4,096, 64x64 tanh MLPs, log std annealed (SB3:"
        " fixed at -0.7), lr adapted to the KL (SB3: constant)",
    },
    # The paper's three humanoid tasks (roboschool_humanoid.py) are env-bound at 50M steps: each env alone,
    # beside gymnasium's Humanoid-v5, reset when its episode ends.
    "roboschool": {
        "env_id": "Humanoid-v5",
        "steps": 5000,
        "ours": [],
        "peers": [],
        "envs": [
            f"roboschool_humanoid:{task}-v0" for task in ("HumanoidForward", "HumanoidFlagrun", "HumanoidFlagrunHarder")
        ],
        "settings": "each env alone with random actions in [-1, 1] (Humanoid-v5's own action space: [-0.4, 0.4])",
    },
    # The same tasks' own vector env (the rules computed once over N bodies) beside a SyncVectorEnv of single envs and
    # the physics alone, 64 envs each; and training with Table 4 on 2 ranks with either.
    "roboschool-vector": {
        "env_id": ROBOSCHOOL[1],
        "steps": 3 * 128 * 512,  # training: 3 iterations of Table 4's 128 actors; the envs alone: 150 steps of 64
        "ours": [
            "torchrun --nproc-per-node 2 ppo_continuous.py +single-envs",
            "torchrun --nproc-per-node 2 ppo_continuous.py",
        ],
        "peers": [],
        "flags": shlex.join(TABLE4_128) + " --torch-threads 1",
        "vector": [f"{kind} {task}" for task in ROBOSCHOOL for kind in ("physics", "sync", "vector")],
    },
}


# WORKERS: each runs in its own process and prints one JSON line {"sps": ...}.


def steady_rate(start, ends):
    """(steps/s from the first iteration's end to the last's, seconds to the first end); ends: [(step, time)]."""
    (first_step, first_time), (last_step, last_time) = ends[0], ends[-1]
    return (last_step - first_step) / (last_time - first_time), first_time - start


def measure_ours(case, env_id, steps, suite_flags=""):
    import torch
    import torch.distributed as dist
    import tyro
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    script, *flags = case.split()
    module = load_script(script)
    if "+single-envs" in flags:  # the id's envs as a SyncVectorEnv of single envs, as before it had its own vector env
        import importlib

        import gymnasium as gym

        flags.remove("+single-envs")
        module_name, _, name = env_id.rpartition(":")
        importlib.import_module(module_name)
        gym.spec(name).vector_entry_point = None
    if "WORLD_SIZE" in os.environ:  # a torchrun case: this process is one rank, as the script's main() makes it
        dist.init_process_group("gloo")
    with tempfile.TemporaryDirectory() as tmp:
        args = tyro.cli(
            module.Args,
            args=[*suite_flags.split(), *flags, "--env-id", env_id, "--total-timesteps", str(steps), "--run-dir", tmp],
        )  # the defaults, but for the suite's flags and the case's
        module.check_args(args)
        torch.set_num_threads(args.torch_threads)  # as the script's main() sets the process up before train()
        start = time.time()
        module.train(args)
        if dist.is_initialized() and dist.get_rank() > 0:
            return None  # rank 0 keeps the run's record, and reports
        acc = EventAccumulator(tmp)
        acc.Reload()
        return steady_rate(start, [(e.step, e.wall_time) for e in acc.Scalars("charts/SPS")])


def rollout_ends():
    """An SB3 callback that records (steps, time) at the end of each rollout."""
    from stable_baselines3.common.callbacks import BaseCallback

    class Ends(BaseCallback):
        def __init__(self):
            super().__init__()
            self.ends = []

        def _on_step(self):
            return True

        def _on_rollout_end(self):
            self.ends.append((self.num_timesteps, time.time()))

    return Ends()


def measure_sb3_ppo_mujoco(
    env_id, steps, threads=None, n_envs=1, n_steps=2048, batch_size=64, n_epochs=10, anneal_lr=True, log_std_init=0.0
):
    import gymnasium as gym
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    # SB3 as its users run it leaves torch at its default number of threads (one per core). On 2
    # cores the intra-op threads slow 64x64 MLPs down, so we also measure it with 1 thread, as ours.
    if threads is not None:
        torch.set_num_threads(threads)
    envs = VecNormalize(DummyVecEnv([lambda: gym.make(env_id)] * n_envs), gamma=0.99)
    model = PPO(
        "MlpPolicy",
        envs,
        n_steps=n_steps,
        batch_size=batch_size,
        n_epochs=n_epochs,
        learning_rate=(lambda progress_remaining: 3e-4 * progress_remaining) if anneal_lr else 3e-4,
        gamma=0.99,
        gae_lambda=0.95,
        clip_range=0.2,
        ent_coef=0.0,
        vf_coef=0.5,
        max_grad_norm=0.5,
        policy_kwargs=dict(
            net_arch=dict(pi=[64, 64], vf=[64, 64]), activation_fn=torch.nn.Tanh, log_std_init=log_std_init
        ),
        device="cpu",
        seed=1,
        verbose=0,
    )
    return learn(model, steps)


def learn(model, steps):
    """SB3's steady rate, measured as ours: from the end of its first iteration to the end of its last.
    SB3 updates after each rollout end, so one more rollout closes the last update."""
    ends, start = rollout_ends(), time.time()
    model.learn(total_timesteps=steps + model.n_steps * model.n_envs, callback=ends)
    return steady_rate(start, ends.ends[1:])


# The paper's Table 5 (ppo_atari.py's defaults) as SB3's PPO takes them: alpha anneals the step size and the clip range.
SB3_TABLE5 = {
    "n_steps": 128,
    "batch_size": 256,
    "n_epochs": 3,
    "learning_rate": lambda progress_remaining: 2.5e-4 * progress_remaining,
    "clip_range": lambda progress_remaining: 0.1 * progress_remaining,
    "gamma": 0.99,
    "gae_lambda": 0.95,
    "ent_coef": 0.01,
    "vf_coef": 1.0,
    "max_grad_norm": 0.5,
}


def measure_sb3_ppo_atari(env_id, steps):
    import ale_py
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_atari_env
    from stable_baselines3.common.vec_env import VecFrameStack

    gym.register_envs(ale_py)
    # SB3's Atari wrappers (noop, skip+max, episodic life, fire reset, 84x84 gray, clipped reward)
    # and a 4-frame stack, with the paper's Table 5 settings as in ppo_atari.py.
    envs = VecFrameStack(make_atari_env(env_id, n_envs=8, seed=1), n_stack=4)
    model = PPO("CnnPolicy", envs, **SB3_TABLE5, device="cpu", seed=1, verbose=0)
    return learn(model, steps)


def measure_atari_env(env_id, steps):
    import numpy as np

    module = load_script("ppo_atari.py")
    envs = module.make_envs(module.Args(env_id=env_id))  # the env exactly as ppo_atari.py makes it
    envs.reset(seed=1)
    rng = np.random.default_rng(1)
    start = time.perf_counter()
    for _ in range(steps // envs.num_envs):
        envs.step(rng.integers(0, envs.single_action_space.n, size=envs.num_envs))
    return steps / (time.perf_counter() - start), None


def measure_vector_env(env_id, steps, suite_flags):
    """The envs alone, as ppo_continuous.py makes them from the suite's flags, stepped with random actions."""
    import numpy as np
    import tyro

    module = load_script("ppo_continuous.py")
    args = tyro.cli(module.Args, args=[*suite_flags.split(), "--env-id", env_id])
    envs = module.make_envs(args, None, None)
    envs.reset(seed=list(range(envs.num_envs)))
    envs.action_space.seed(1)
    start = time.perf_counter()
    for _ in range(steps // envs.num_envs):
        envs.step(np.clip(envs.action_space.sample(), -0.4, 0.4))
    return steps / (time.perf_counter() - start), None


def measure_roboschool_vector(case, num_envs=64, steps=150):
    """64 envs of a roboschool task, stepped with the same random actions: a SyncVectorEnv of single envs, the task's
    own vector env, or the physics alone: the time that vector env spends in mj_step, on the same steps."""
    import gymnasium as gym
    import mujoco
    import numpy as np

    kind, env_id = case.split()
    if kind == "sync":
        envs = gym.vector.SyncVectorEnv(
            [lambda: gym.make(env_id)] * num_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
        )
    else:
        envs = gym.make_vec(env_id, num_envs, vectorization_mode="vector_entry_point")
    envs.reset(seed=list(range(num_envs)))
    actions = np.clip(np.random.default_rng(1).normal(0.0, 0.3, (steps, num_envs, 17)), -1, 1).astype(np.float32)
    physics, mj_step = [0.0], mujoco.mj_step

    def timed_mj_step(*args, **kwargs):
        start = time.perf_counter()
        mj_step(*args, **kwargs)
        physics[0] += time.perf_counter() - start

    if kind == "physics":
        mujoco.mj_step = timed_mj_step
    start = time.perf_counter()
    for action in actions:
        envs.step(action)
    return steps * num_envs / (physics[0] if kind == "physics" else time.perf_counter() - start), None


def measure_env(env_id, steps):
    import gymnasium as gym

    env = gym.make(env_id)
    env.reset(seed=1)
    env.action_space.seed(1)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, term, trunc, _ = env.step(env.action_space.sample())
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - start), None


def run_worker(case, env_id, steps, suite):
    suite_flags = SUITES[suite].get("flags", "")
    if case.startswith("ppo_"):
        sps = measure_ours(case, env_id, steps, suite_flags)
        if sps is None:  # a rank > 0 of a torchrun case
            return
    elif case.startswith("sb3_ppo_humanoid"):
        # Table 4: SB3 has no KL-adapted lr nor log std schedule: a constant lr, and the schedule's first log std
        table4 = dict(n_envs=32, n_steps=512, batch_size=4096, n_epochs=15, anneal_lr=False, log_std_init=-0.7)
        sps = measure_sb3_ppo_mujoco(env_id, steps, 1 if case.endswith("1thread") else None, **table4)
    elif case == "env" and suite_flags:
        sps = measure_vector_env(env_id, steps, suite_flags)
    elif case == "sb3_ppo_atari":
        sps = measure_sb3_ppo_atari(env_id, steps)
    elif case == "env" and "NoFrameskip" in env_id:
        sps = measure_atari_env(env_id, steps)
    elif case == "sb3_ppo_mujoco":
        sps = measure_sb3_ppo_mujoco(env_id, steps)
    elif case == "sb3_ppo_mujoco_1thread":
        sps = measure_sb3_ppo_mujoco(env_id, steps, threads=1)
    elif case == "env":
        sps = measure_env(env_id, steps)
    elif case.split()[0] in ("physics", "sync", "vector"):
        sps = measure_roboschool_vector(case)
    elif case.startswith("env "):  # an env of an env suite, alone
        sps = measure_env(case.split()[1], steps)
    else:
        raise ValueError(case)
    print(json.dumps({"sps": sps[0], "first_iteration_s": sps[1]}))


# ORCHESTRATION


def measure(case, env_id, steps, suite):
    launcher = [sys.executable]
    if case.startswith("torchrun"):  # torchrun --nproc-per-node P <case>: P ranks of one run on this machine
        _, nproc, processes, case = case.split(maxsplit=3)
        launcher += ["-m", "torch.distributed.run", "--standalone", f"{nproc}={processes}"]
    cmd = [*launcher, __file__, "--worker", case, "--env-id", env_id, "--steps", str(steps), "--suite", suite]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"{case} failed:\n{proc.stderr[-3000:]}")
    # The worker's one JSON line; under torchrun the other ranks' own lines may come after it.
    result = json.loads(next(line for line in reversed(proc.stdout.splitlines()) if line.startswith("{")))
    return result["sps"], result["first_iteration_s"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--suite", choices=["all", *sorted(SUITES)], default="all")
    parser.add_argument("--steps", type=int, help="env steps per measurement (default: the suite's, a few rollouts)")
    parser.add_argument("--repeats", type=int, default=3, help="measurements of each case, taken in alternation")
    parser.add_argument("--no-write", action="store_true", help="print the table but do not write the results file")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--env-id", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        return run_worker(args.worker, args.env_id, args.steps, args.suite)
    if (args.steps is not None and args.steps <= 0) or args.repeats <= 0:
        parser.error("--steps and --repeats must be positive")
    for name in list(SUITES) if args.suite == "all" else [args.suite]:
        table = measure_suite(name, args.steps or SUITES[name]["steps"], args.repeats)
        print("\n" + table)
        if not args.no_write:
            write_section(RESULTS / "throughput.md", name, table)
            print(f"wrote the {name} section of {(RESULTS / 'throughput.md').relative_to(ROOT)}")


def write_section(path, name, table):
    """Put `table` in the file's section for suite `name`, keeping every other suite's section."""
    start, end = f"<!-- suite: {name} -->", f"<!-- end of suite: {name} -->"
    text = path.read_text() if path.exists() else ""
    if not text.startswith("# Throughput"):
        text = (
            "# Throughput\n\nGenerated by `benchmarks/throughput.py`, one section per suite, each from its own run;"
            " do not edit by hand.\n"
        )
    section = f"{start}\n{table.rstrip()}\n{end}"
    text = replace_between(text, start, end, section) or text.rstrip() + "\n\n" + section + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def measure_suite(name, steps, repeats):
    """Measure one suite's cases in alternation; return its markdown table."""
    suite = SUITES[name]
    env_id = suite["env_id"]
    ours = [case for case in suite["ours"] if (ROOT / next(w for w in case.split() if w.endswith(".py"))).exists()]
    cases = [*ours, *suite["peers"], "env", *(f"env {env}" for env in suite.get("envs", []))]
    if "vector" in suite:
        cases = [*ours, *suite["vector"]]
    load_at_start = os.getloadavg()[0]
    samples, firsts = {case: [] for case in cases}, {case: [] for case in cases}
    total, done, start = len(cases) * repeats, 0, time.time()
    for _ in range(repeats):
        for case in cases:
            sps, first = measure(case, env_id, steps, name)
            samples[case].append(sps)
            firsts[case].append(first)
            done += 1
            eta = (time.time() - start) / done * (total - done)
            print(f"[{done}/{total}] {case:<28} {sps:8.0f} steps/s   (ETA {eta:4.0f} s)", flush=True)

    median = {case: statistics.median(v) for case, v in samples.items()}
    first = {case: statistics.median(v) if None not in v else None for case, v in firsts.items()}
    command = "python benchmarks/throughput.py " + " ".join(sys.argv[1:])
    if "vector" in suite:
        return vector_table(name, suite, cases, samples, median, steps, repeats, load_at_start, command)
    peers, env = suite["peers"], median["env"]
    if "envs" in suite:
        return env_table(name, suite, cases, samples, median, steps, repeats, load_at_start, command)
    lines = [
        f"## {name} ({env_id})",
        "",
        "| case | median steps/s | samples | "
        + " | ".join(f"ratio to {p}" for p in peers)
        + " | fraction of env-only | first iteration |",
        "|---|---|---|" + "---|" * len(peers) + "---|---|",
    ]
    for case in cases:
        ratios = " | ".join(f"{median[case] / median[p]:.2f}x" for p in peers)
        first_s = f"{first[case]:.1f} s" if first[case] is not None else "–"
        lines.append(
            f"| {case} | {median[case]:.0f} | {', '.join(f'{s:.0f}' for s in samples[case])} | {ratios}"
            f" | {median[case] / env:.2f} | {first_s} |"
        )
    for case in ours:
        eager = case.replace(" --compile", "")
        if case.startswith("torchrun"):
            one = next(w for w in case.split() if w.endswith(".py"))
            lines += ["", f"- `{case}`: {median[case] / median[one]:.2f}x `{one}` in one process (medians)."]
        if case != eager and first[eager] is not None:
            lines += [
                "",
                f"- Compilation: `{case}` takes {first[case] - first[eager]:.1f} s longer than `{eager}`"
                " to the end of its first iteration (medians); that is torch.compile's one-off cost,"
                " left out of the steps/s.",
            ]
    lines += [
        "",
        f"- Settings: {env_id}, {suite['settings']};"
        f" {steps:,} steps per measurement, {repeats} measurements of each case, in alternation; the median is shown.",
        "- Steps/s is the steady rate, from the end of the first iteration (rollout and update) to the end of the last;"
        " 'first iteration' is the time from the start of `train()` or `learn()` to the end of the first.",
        "- Peers: Stable-Baselines3's PPO with the same hyperparameters and network;"
        " `sb3_ppo_mujoco` (with VecNormalize) and `sb3_ppo_atari` (with its Atari wrappers and a 4-frame stack)"
        " run with torch's default threads, as SB3 users run it, `sb3_ppo_mujoco_1thread` with 1 thread,"
        " as ppo_continuous.py. `env` is the environment alone with random actions"
        " (for Atari, ale-py's vector env as ppo_atari.py makes it).",
        *(
            [
                f"- Every case of ours adds `{suite['flags']}` (the `humanoid` suite of `benchmarks/run.py`);"
                " `sb3_ppo_humanoid` steps its 32 envs in SB3's usual DummyVecEnv, with VecNormalize;"
                " `env` steps the 32 envs of ppo_continuous.py's SyncVectorEnv alone."
            ]
            if "flags" in suite
            else []
        ),
        *provenance_lines(load_at_start, command),
    ]
    return "\n".join(lines) + "\n"


def provenance_lines(load_at_start, command):
    return [
        "- The other process sharing the machine during the run, if any, is not controlled:"
        f" compare ratios, not absolute figures (load average at the start: {load_at_start:.1f}).",
        f"- Command: `{command.strip()}`",
        f"- Commit: {commit(['*.py'], ' (with uncommitted changes)')}; date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"- Versions: {versions(('torch', 'numpy', 'gymnasium', 'mujoco', 'ale-py', 'stable-baselines3'))}",
        f"- Machine: {machine()}",
    ]


def vector_table(name, suite, cases, samples, median, steps, repeats, load_at_start, command):
    """The vector suite's table: training with either envs, then each task's envs alone as a share of its physics."""
    old, new = suite["ours"]
    lines = [f"## {name}", "", "| case | median steps/s | samples | ratio |", "|---|---|---|---|"]
    for case in cases:
        kind, *rest = case.split()
        base = old if kind == "torchrun" else f"physics {rest[0]}"
        ratio = f"{median[case] / median[base]:.2f}" + (f"x `{old}`" if kind == "torchrun" else " of the physics")
        lines.append(f"| {case} | {median[case]:.0f} | {', '.join(f'{s:.0f}' for s in samples[case])} | {ratio} |")
    lines += [
        "",
        f"- Training: {suite['env_id']} with `{suite['flags']}`, {steps:,} steps per measurement, the steady rate"
        " (from the first iteration's end to the last's); `+single-envs` makes the envs a SyncVectorEnv of single"
        " envs, as the script did before the ids had their own vector env.",
        "- The envs alone: 64 envs, 150 steps of the same random actions (normal, std 0.3, clipped to [-1, 1]):"
        " `sync` gymnasium's SyncVectorEnv of 64 single envs, `vector` the task's own vector env (`gym.make_vec`),"
        " `physics` the time that vector env spends in MuJoCo's `mj_step` (4 an env step) on the same steps.",
        f"- {repeats} measurements of each case, in alternation, each in a fresh process; the median is shown.",
        *provenance_lines(load_at_start, command),
    ]
    return "\n".join(lines) + "\n"


def env_table(name, suite, cases, samples, median, steps, repeats, load_at_start, command):
    """An env suite's table: each env alone, and its ratio to the suite's env_id."""
    base = suite["env_id"]
    lines = [f"## {name} (envs alone, beside {base})", "", f"| env | median steps/s | samples | ratio to {base} |"]
    lines.append("|---|---|---|---|")
    for case in cases:
        label = base if case == "env" else case.split()[1]
        row = f"| {label} | {median[case]:.0f} | {', '.join(f'{s:.0f}' for s in samples[case])}"
        lines.append(f"{row} | {median[case] / median['env']:.2f}x |")
    lines += [
        "",
        f"- Settings: {suite['settings']}; {steps:,} steps per measurement, reset when an episode ends,"
        f" {repeats} measurements of each env in alternation, each in a fresh process; the median is shown.",
        *provenance_lines(load_at_start, command),
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
