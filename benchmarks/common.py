"""What the benchmark scripts share: loading a script by path, describing the machine, and the
results CSVs (a header of '# key: value' lines, then one row per episode)."""

import csv
import importlib.util
import os
import platform
import signal
import statistics
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def load_script(name):
    """Import one of the ppo_*.py scripts as a module, without running its __main__. Its module name is
    prefixed, so that it never replaces a module of the same file that someone else imported (the tests'
    doctests, for one, find a module's examples through sys.modules)."""
    spec = importlib.util.spec_from_file_location("benchmarks_" + Path(name).stem, ROOT / name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


def git(*args):
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT).stdout.strip()


def commit(paths=(), mark=""):
    """The short hash of HEAD ('unknown' outside git), and `mark` after it when a file of `paths` (git pathspecs)
    differs from it: the one answer to "which commit" that every results file records."""
    rev = git("rev-parse", "--short", "HEAD") or "unknown"
    return rev + (mark if paths and git("status", "--porcelain", "--", *paths) else "")


def versions(packages=("torch", "numpy", "gymnasium", "mujoco")):
    from importlib.metadata import PackageNotFoundError, version

    out = [f"python {platform.python_version()}"]
    for package in packages:
        try:
            out.append(f"{package} {version(package)}")
        except PackageNotFoundError:
            out.append(f"{package} not installed")
    return ", ".join(out)


def machine():
    cpu = platform.processor() or "unknown CPU"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.machine()}"


# The update's statistics that every script logs, kept per iteration beside a run's CSV (<suite>/updates/).
UPDATE_STATS = ("entropy", "approx_kl", "clipfrac", "explained_variance", "value_loss")


def read_run(run_dir):
    """A finished run directory's checkpoint, its episodes (step, return, length), for a run of
    ppo_kl_penalty.py beta's range and its series: (step, beta, the update's mean KL) per iteration,
    and the UPDATE_STATS per iteration: (step, *stats), or None for a script that logs none (SB3)."""
    import torch
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    returns = acc.Scalars("charts/episodic_return")
    lengths = acc.Scalars("charts/episodic_length")
    checkpoint = torch.load(Path(run_dir) / "checkpoint.pt", map_location="cpu", weights_only=True)
    rows = [(ret.step, ret.value, int(length.value)) for ret, length in zip(returns, lengths, strict=True)]
    beta, series = None, None
    if "losses/beta" in acc.Tags()["scalars"]:
        series = [
            (b.step, b.value, k.value)
            for b, k in zip(acc.Scalars("losses/beta"), acc.Scalars("losses/kl"), strict=True)
        ]
        # ppo_kl_penalty.py: the range of beta over the whole run and over its first 90% of updates
        betas = [e.value for e in acc.Scalars("losses/beta")]
        early = betas[: int(0.9 * len(betas))] or betas
        beta = f"{min(betas):.3g}..{max(betas):.3g} (first 90% of updates: {min(early):.3g}..{max(early):.3g})"
    tags = acc.Tags()["scalars"]
    updates = None
    if all(f"losses/{name}" in tags for name in UPDATE_STATS):
        columns = [acc.Scalars(f"losses/{name}") for name in UPDATE_STATS]
        updates = [(events[0].step, *(e.value for e in events)) for events in zip(*columns, strict=True)]
    return checkpoint, rows, beta, series, updates


# ppo_rlhf.py's rlhf/* scalars, kept per iteration beside a run's CSV (<suite>/rlhf/).
RLHF_STATS = (
    "score",
    "gold_score",
    "kl",
    "kl_coef",
    "entropy",
    "response_length",
    "eos_fraction",
    "well_formed",
    "rm_accuracy",
    "spam",
    "garbled",
    "rm_pairs",
)


def read_rlhf(run_dir):
    """A run's rlhf/* scalars per iteration, (step, *RLHF_STATS), or None for a script that logs none."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    if not all(f"rlhf/{name}" in acc.Tags()["scalars"] for name in RLHF_STATS):
        return None
    columns = [acc.Scalars(f"rlhf/{name}") for name in RLHF_STATS]
    return [(events[0].step, *(e.value for e in events)) for events in zip(*columns, strict=True)]


def write_csv(path, header, rows):
    """A results CSV: '# key: value' header lines, then global_step, episodic_return, episodic_length."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        for key, value in header:
            f.write(f"# {key}: {value}\n")
        writer = csv.writer(f)
        writer.writerow(["global_step", "episodic_return", "episodic_length"])
        writer.writerows(rows)
    os.replace(tmp, path)  # a CSV is there in full or not at all: its presence means "finished"


def read_csv(path):
    meta, rows = {}, []
    with open(path) as f:
        for line in f:
            if line.startswith("# "):
                key, _, value = line[2:].partition(": ")
                meta[key] = value.strip()
            else:
                break
    with open(path) as f:
        reader = csv.DictReader(line for line in f if not line.startswith("#"))
        rows = [(int(r["global_step"]), float(r["episodic_return"]), int(r["episodic_length"])) for r in reader]
    return meta, rows


def score(rows):
    """A run's score: the mean return of its last 100 episodes."""
    return statistics.mean(r for _, r, _ in rows[-100:])


def replace_between(text, start, end, block):
    """`text` with everything from the marker `start` to the marker `end` replaced by `block`
    (which carries the markers itself), or None when `text` lacks a marker."""
    if start not in text or end not in text:
        return None
    head, rest = text.split(start, 1)
    return head + block + rest.split(end, 1)[1]


def sb3_main(script, Args, check_args, make_model, default_run_dir, save_every_steps, episode_length=lambda n: n):
    """The main() of an SB3 peer (sb3_atari.py, sb3_mujoco.py), which run.py runs as it runs our scripts: a one-line
    error and exit 2 for bad input; TensorBoard's charts/episodic_return (Monitor's undiscounted return) and
    charts/episodic_length (`episode_length` of Monitor's length); the model, the VecNormalize statistics if any
    and a checkpoint.pt with the step, saved every `save_every_steps(args)` steps, at the end and on Ctrl-C or
    SIGTERM (then exit 130); and --resume, which continues a run with the arguments it was started with.
    make_model(args, run_dir) -> (model, model_path) loads the model saved there, if any."""
    import tyro

    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        print(f"{script}: error: {e}", file=sys.stderr)
        sys.exit(2)
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from torch.utils.tensorboard import SummaryWriter

    if args.resume is not None:
        saved = torch.load(args.resume, map_location="cpu", weights_only=True)
        runtime = {key: getattr(args, key) for key in ("torch_threads", "save_every", "resume")}
        args = Args(**{**saved["args"], **runtime, "run_dir": os.path.dirname(os.path.abspath(args.resume))})
    run_dir = args.run_dir or default_run_dir(args)
    os.makedirs(run_dir, exist_ok=True)
    torch.set_num_threads(args.torch_threads)
    model, model_path = make_model(args, run_dir)
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    writer = SummaryWriter(run_dir, purge_step=model.num_timesteps + 1 if args.resume else None)
    stop = []  # Ctrl-C and SIGTERM only set this flag; the callback ends learn() at the next step
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))

    def save():
        model.save(model_path)
        if model.get_vec_normalize_env() is not None:
            model.get_vec_normalize_env().save(os.path.join(run_dir, "vecnormalize.pkl"))
        writer.flush()
        checkpoint = {"format": "sb3-checkpoint-v1", "args": asdict(args), "global_step": model.num_timesteps}
        torch.save(checkpoint, f"{checkpoint_path}.tmp")
        os.replace(f"{checkpoint_path}.tmp", checkpoint_path)

    class Log(BaseCallback):
        saved_at = printed_at = model.num_timesteps

        def _on_step(self):
            for info in self.locals["infos"]:
                if "episode" in info:  # an episode ended: Monitor sits below every wrapper that changes rewards
                    writer.add_scalar("charts/episodic_return", info["episode"]["r"], self.num_timesteps)
                    writer.add_scalar(
                        "charts/episodic_length", episode_length(info["episode"]["l"]), self.num_timesteps
                    )
            return not stop

        def _on_rollout_end(self):
            if self.num_timesteps - Log.saved_at >= save_every_steps(args):
                Log.saved_at = self.num_timesteps
                save()
            if self.num_timesteps - Log.printed_at >= 10_000 or self.num_timesteps >= args.total_timesteps:
                Log.printed_at = self.num_timesteps
                print(f"step {self.num_timesteps:,}/{args.total_timesteps:,}", flush=True)

    model.learn(args.total_timesteps - model.num_timesteps, callback=Log(), reset_num_timesteps=False)
    save()
    writer.close()
    if stop:
        print(f"stopped: saved step {model.num_timesteps:,}; continue with --resume {checkpoint_path}")
        sys.exit(130)
    print(f"saved {checkpoint_path}")
