"""The results folder, benchmarks/results/<folder>/, in both directions: what run.py writes of a finished run and what
the reports read back. Its one owner, so that the format is written down once.

A suite's folder holds one CSV a run, <env>__<variant>__seed<N>.csv: '# key: value' header lines (the command, commit,
package versions, machine, wall time, ...), then global_step, episodic_return, episodic_length, a row an episode. Beside
them, per run and per iteration, the series a run logged: beta/ (an adaptive or fixed KL penalty's beta and the update's
KL), updates/ (UPDATE_STATS), rlhf/ (RLHF_STATS), ensemble/ (ENSEMBLE_STATS), kto/ (KTO_STATS), process/
(PROCESS_STATS), and samples/ (the responses an RLHF run printed last); best_of_n/seed<N>.csv is
benchmarks/best_of_n.py's. results/random/<env>.csv is the random policy's (benchmarks/random_score.py), and
benchmarks/reference_figures.csv the published figures.
"""

from __future__ import annotations

import csv
import os
import platform
import re
import statistics
import subprocess
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
REFERENCE = ROOT / "benchmarks" / "reference_figures.csv"

# The update's statistics that every script logs (losses/*), kept per iteration beside a run's CSV (<folder>/updates/).
UPDATE_STATS = ("entropy", "approx_kl", "clipfrac", "explained_variance", "value_loss")

# ppo_rlhf.py's rlhf/* scalars, kept per iteration beside a run's CSV (<folder>/rlhf/).
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

# What rlhf/rm_accuracy measures, in the CSV header of each RLHF run that measured it so (ppo_rlhf.py from 605ebaa on):
# before, a pool of every rollout's first 16 responses, mostly pairs to different prompts, which the RM never learned.
RM_ACCURACY = "pairs to one prompt among the last 640 responses"
# An --rm-ensemble run's members (ppo_rlhf.py's rlhf/rm_disagreement and rlhf/rm_member<k>), in <folder>/ensemble/.
ENSEMBLE_STATS = ("rm_disagreement",)
# A --kto run's reference point z0, and the mismatched pairs' mean implied reward that it clamps (losses/*), in
# <folder>/kto/.
KTO_STATS = ("kto_z0", "kto_mismatched_reward")
# A --reward process run's share of the policy's clauses its reward model rates good or bad as gold does (rlhf/*), in
# <folder>/process/.
PROCESS_STATS = ("rm_clause_accuracy",)
# What an RLHF run's reward_model.pt says of its reward model, in the run's CSV header as rm_<fact>: a process RM's
# accuracy on held-out clauses and the labels it cost (clauses), and the comparisons its stage 2 trained on (an
# outcome RM's too, from ppo_rlhf.py's --rm-refresh on); and from the run's checkpoint.pt, rm_refresh_labels, the
# labels a --rm-refresh run's reward model learned from on the policy's text.
RM_FACTS = ("held_out_clause_accuracy", "clause_labels", "train_pairs")

# best_of_n.py's columns, in <folder>/best_of_n/seed<N>.csv.
BEST_OF_N = ("n", "kl", "score", "gold_score", "well_formed", "spam", "garbled", "rm_accuracy")


# ---------------------------------------------------------------- what every results file records


def git(*args):
    """What a git command run at the repository's root prints, stripped ('' outside git)."""
    return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT).stdout.strip()


def commit(paths=(), mark=""):
    """The short hash of HEAD ('unknown' outside git), and `mark` after it when a file of `paths` (git pathspecs)
    differs from it: the one answer to "which commit" that every results file records."""
    rev = git("rev-parse", "--short", "HEAD") or "unknown"
    return rev + (mark if paths and git("status", "--porcelain", "--", *paths) else "")


def versions(packages=("torch", "numpy", "gymnasium", "mujoco")):
    """'python X, torch Y, ...': the versions of python and of `packages` ('not installed' for a missing one)."""
    from importlib.metadata import PackageNotFoundError, version

    out = [f"python {platform.python_version()}"]
    for package in packages:
        try:
            out.append(f"{package} {version(package)}")
        except PackageNotFoundError:
            out.append(f"{package} not installed")
    return ", ".join(out)


def machine():
    """'CPU model, N cores, OS arch': the machine a result was made on."""
    cpu = platform.processor() or "unknown CPU"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.machine()}"


# ---------------------------------------------------------------- a finished run directory, read


@dataclass
class RunLogs:
    """What a finished run directory holds: its last step, its episodes, and the series it logged (None where it
    logged none)."""

    global_step: int
    rows: list  # (global_step, episodic_return, episodic_length), one per episode
    beta_range: str | None  # a KL-penalty run: beta's range over the run and over its first 90% of updates
    beta: list | None  # a KL-penalty run: (step, beta, the update's mean KL) per iteration
    updates: list | None  # (step, *UPDATE_STATS) per iteration; None for a script that logs none (SB3)
    rlhf: list | None  # an RLHF run: (step, *RLHF_STATS) per iteration
    rm_held_out_accuracy: float | None  # an RLHF run: its reward model's accuracy on held-out pairs
    samples: list[str]  # an RLHF run: the responses it printed last, with their scores
    ensemble: list | None = None  # an --rm-ensemble run: (step, rm_disagreement, each member's score) per iteration
    kto: list | None = None  # a --kto run: (step, *KTO_STATS) per iteration
    process: list | None = None  # a --reward process run: (step, *PROCESS_STATS) per iteration
    rm_facts: dict | None = None  # an RLHF run: those of RM_FACTS its reward model has, and refresh_labels

    def header(self):
        """The CSV header lines that come from the run's own logs: [(key, value), ...]."""
        return [
            *([("beta_range", self.beta_range)] if self.beta_range else []),
            *([("rm_held_out_accuracy", f"{self.rm_held_out_accuracy:.4f}")] if self.rm_held_out_accuracy else []),
            *(
                (f"rm_{key}", f"{value:.4f}" if isinstance(value, float) else f"{value}")
                for key, value in (self.rm_facts or {}).items()
            ),
            *([("rm_accuracy", RM_ACCURACY)] if self.rlhf else []),
        ]


def scalars(acc, tag_prefix, names):
    """[(step, *values)] per logged step of the TensorBoard scalars <tag_prefix><name> for each of `names`, or None
    unless every one of them was logged."""
    if not all(f"{tag_prefix}{name}" in acc.Tags()["scalars"] for name in names):
        return None
    columns = [acc.Scalars(f"{tag_prefix}{name}") for name in names]
    return [(events[0].step, *(e.value for e in events)) for events in zip(*columns, strict=True)]


def read_run(run_dir):
    """The RunLogs of a finished run directory: its checkpoint's step, its TensorBoard scalars, the reward model's
    held-out accuracy (reward_model.pt) and the samples its log printed (log.txt), where it has them."""
    import torch
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_dir = Path(run_dir)
    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    returns = acc.Scalars("charts/episodic_return")
    lengths = acc.Scalars("charts/episodic_length")
    checkpoint = torch.load(run_dir / "checkpoint.pt", map_location="cpu", weights_only=True)
    rows = [(ret.step, ret.value, int(length.value)) for ret, length in zip(returns, lengths, strict=True)]
    beta_range, beta = None, None
    if "losses/beta" in acc.Tags()["scalars"]:
        beta = [(step, b, kl) for step, b, kl in scalars(acc, "losses/", ("beta", "kl"))]
        # the range of beta over the whole run and over its first 90% of updates
        betas = [b for _, b, _ in beta]
        early = betas[: int(0.9 * len(betas))] or betas
        beta_range = f"{min(betas):.3g}..{max(betas):.3g} (first 90% of updates: {min(early):.3g}..{max(early):.3g})"
    rlhf = scalars(acc, "rlhf/", RLHF_STATS)
    members = sorted(tag[len("rlhf/") :] for tag in acc.Tags()["scalars"] if re.fullmatch(r"rlhf/rm_member\d+", tag))
    return RunLogs(
        global_step=checkpoint["global_step"],
        rows=rows,
        beta_range=beta_range,
        beta=beta,
        updates=scalars(acc, "losses/", UPDATE_STATS),
        rlhf=rlhf,
        rm_held_out_accuracy=held_out_accuracy(run_dir),
        rm_facts=reward_model_facts(run_dir, checkpoint),
        samples=last_samples(run_dir) if rlhf else [],
        ensemble=scalars(acc, "rlhf/", (*ENSEMBLE_STATS, *sorted(members, key=len))) if members else None,
        kto=scalars(acc, "losses/", KTO_STATS),
        process=scalars(acc, "rlhf/", PROCESS_STATS),
    )


def held_out_accuracy(run_dir):
    """How often an RLHF run's reward model ranked held-out pairs of pi_SFT's responses as gold does, from its
    reward_model.pt; None for a run that has none."""
    path = Path(run_dir) / "reward_model.pt"
    if not path.exists():
        return None
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)["held_out_accuracy"]


def reward_model_facts(run_dir, checkpoint):
    """{fact: value} of those of RM_FACTS that an RLHF run's reward_model.pt holds, and refresh_labels from its
    `checkpoint` where it has them; None for a run with neither."""
    path = Path(run_dir) / "reward_model.pt"
    import torch

    saved = torch.load(path, map_location="cpu", weights_only=True) if path.exists() else {}
    facts = {key: saved[key] for key in RM_FACTS if key in saved}
    facts |= {"refresh_labels": checkpoint["refresh_labels"]} if "refresh_labels" in checkpoint else {}
    return facts or None


def last_samples(run_dir, count=3):
    """The last `count` responses a run printed with their scores ('  score ...' lines of its log.txt)."""
    path = Path(run_dir) / "log.txt"
    log = path.read_text().splitlines() if path.exists() else []
    return [line.strip() for line in log if line.startswith("  score ")][-count:]


# ---------------------------------------------------------------- the results folder, written


def write_series(path, columns, rows):
    """A per-iteration series as a CSV: global_step (exact) and then the columns (6 significant digits)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(("global_step", *columns))] + [
        ",".join((f"{step:.0f}", *(f"{x:.6g}" for x in rest))) for step, *rest in rows
    ]
    path.write_text("\n".join(lines) + "\n")


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


def write_run(results_dir, name, header, logs):
    """Write a finished run into its results folder: each series it logged, its samples, then <name>.csv with
    `header` and the logs' own header lines. Returns the CSV's path."""
    results_dir = Path(results_dir)
    if logs.beta:  # beta after each update, for the report's plot of it
        write_series(results_dir / "beta" / f"{name}.csv", ("beta", "kl"), logs.beta)
    if logs.updates:  # the update's statistics per iteration, for the report's diagnostics
        write_series(results_dir / "updates" / f"{name}.csv", UPDATE_STATS, logs.updates)
    if logs.rlhf:  # the rlhf/* scalars per iteration, and the responses the run printed last
        write_series(results_dir / "rlhf" / f"{name}.csv", RLHF_STATS, logs.rlhf)
        (results_dir / "samples").mkdir(parents=True, exist_ok=True)
        if logs.ensemble:
            members = [f"rm_member{k}" for k in range(len(logs.ensemble[0]) - 1 - len(ENSEMBLE_STATS))]
            write_series(results_dir / "ensemble" / f"{name}.csv", (*ENSEMBLE_STATS, *members), logs.ensemble)
        if logs.kto:
            write_series(results_dir / "kto" / f"{name}.csv", KTO_STATS, logs.kto)
        if logs.process:
            write_series(results_dir / "process" / f"{name}.csv", PROCESS_STATS, logs.process)
        (results_dir / "samples" / f"{name}.txt").write_text("".join(f"{line}\n" for line in logs.samples))
    path = results_dir / f"{name}.csv"
    write_csv(path, [*header, *logs.header()], logs.rows)  # last: the CSV's presence means the run is finished
    return path


def copy_run(source, results_dir, name):
    """Copy a finished run's CSV, and the beta and updates series that go with it, into another results folder
    under `name`."""
    import shutil

    results_dir = Path(results_dir)
    results_dir.mkdir(parents=True, exist_ok=True)
    for series in ("beta", "updates"):
        if (source.parent / series / source.name).exists():
            (results_dir / series).mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source.parent / series / source.name, results_dir / series / f"{name}.csv")
    shutil.copyfile(source, results_dir / f"{name}.csv")  # last, as in write_run


# ---------------------------------------------------------------- the results folder, read


def read_csv(path):
    """A results CSV's header as {key: value}, and its rows: [(global_step, episodic_return, episodic_length)]."""
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


@dataclass
class Run:
    """A finished run, as its CSV has it."""

    env_id: str
    variant: str
    seed: int
    rows: list  # (global_step, episodic_return, episodic_length)
    meta: dict

    @property
    def score(self):
        return score(self.rows)


def run_files(folder):
    """(env_id, variant, seed, path) for every <env>__<variant>__seed<N>.csv in a folder, sorted by name."""
    for path in sorted(Path(folder).glob("*__*__seed*.csv")):
        env_id, variant, seed = path.stem.split("__")
        yield env_id, variant, int(seed.removeprefix("seed")), path


def load_runs(folder):
    """Every Run of a results folder, sorted by file name."""
    runs = []
    for env_id, variant, seed, path in run_files(folder):
        meta, rows = read_csv(path)
        runs.append(Run(env_id, variant, seed, rows, meta))
    return runs


def read_beta(folder):
    """{(env_id, variant, seed): [(step, beta, kl), ...]} from <folder>/beta/."""
    out = {}
    for env_id, variant, seed, path in run_files(Path(folder) / "beta"):
        with open(path) as f:
            out[env_id, variant, seed] = [
                (int(r["global_step"]), float(r["beta"]), float(r["kl"])) for r in csv.DictReader(f)
            ]
    return out


def read_updates(folder):
    """{(env_id, variant, seed): [[step, *UPDATE_STATS], ...]} from <folder>/updates/, as floats."""
    out = {}
    for env_id, variant, seed, path in run_files(Path(folder) / "updates"):
        with open(path) as f:
            out[env_id, variant, seed] = [[float(x) for x in row.values()] for row in csv.DictReader(f)]
    return out


def read_rlhf_series(folder):
    """{(variant, seed): numpy array [iterations, 1 + len(RLHF_STATS)]} from <folder>/rlhf/."""
    import numpy as np

    return {
        (variant, seed): np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        for _, variant, seed, path in run_files(Path(folder) / "rlhf")
    }


def read_ensemble_series(folder):
    """{(variant, seed): numpy array [iterations, 1 + len(ENSEMBLE_STATS) + K]} from <folder>/ensemble/."""
    import numpy as np

    return {
        (variant, seed): np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        for _, variant, seed, path in run_files(Path(folder) / "ensemble")
    }


def read_series(folder, series):
    """{(variant, seed): numpy array [iterations, 1 + len(columns)]} of an optional series, kto/ (KTO_STATS) or
    process/ (PROCESS_STATS), from <folder>/<series>/."""
    import numpy as np

    return {
        (variant, seed): np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        for _, variant, seed, path in run_files(Path(folder) / series)
    }


def read_best_of_n(folder):
    """{seed: (meta, numpy array [Ns, len(BEST_OF_N)])} from <folder>/best_of_n/, which best_of_n.py writes."""
    import numpy as np

    out = {}
    for path in sorted((Path(folder) / "best_of_n").glob("seed*.csv")):
        lines = path.read_text().splitlines()
        meta = dict(line[2:].split(": ", 1) for line in lines if line.startswith("# "))
        rows = [line for line in lines if not line.startswith("#")]
        assert rows[0] == ",".join(BEST_OF_N), f"{path}: columns {rows[0]}"
        out[int(path.stem.removeprefix("seed"))] = (meta, np.loadtxt(rows[1:], delimiter=",", ndmin=2))
    return out


def random_score(env_id, results=RESULTS):
    """The random policy's mean return on env_id, or None if random_score.py has not measured it."""
    path = Path(results) / "random" / f"{env_id.replace('/', '-')}.csv"
    if not path.exists():
        return None
    with open(path) as f:
        return statistics.mean(
            float(r["episodic_return"]) for r in csv.DictReader(line for line in f if not line.startswith("#"))
        )


def load_reference(path=REFERENCE):
    """{(column, env, setting): (score, std or None, source)} from the reference data file."""
    with open(path) as f:
        reader = csv.DictReader(line for line in f if not line.startswith("#"))
        return {
            (r["column"], r["env"], r["setting"]): (
                float(r["score"]),
                float(r["std"]) if r["std"] else None,
                r["source"],
            )
            for r in reader
        }
