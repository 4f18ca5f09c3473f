"""What every suite's report shares: the rule a score follows, the numbers' format, the provenance lines, the table
of every run, the learning curves, and which suite and report module a results folder belongs to (stats.py has the
statistics over seeds)."""

from __future__ import annotations

import importlib
import math
import re
import statistics
import warnings
from pathlib import Path

from results import ROOT
from suites import COLUMNS, SUITES

SCORE_RULE = (
    "A run's score is the mean return of its last 100 episodes; a cell is the mean ± sample std over seeds,"
    " with the number of seeds in brackets."
)
MUJOCO_VERSIONS = (
    "Our MuJoCo tasks are gymnasium's -v5 where the env column does not name another version"
    " (the paper used gym's -v1, CleanRL -v4)."
)


def env_base(env_id):
    """'Hopper-v5' -> 'Hopper'; 'BreakoutNoFrameskip-v4' -> 'Breakout': the key of the reference figures."""
    return env_id.split("-v")[0].replace("NoFrameskip", "").removeprefix("ALE/")


def fmt(mean, std=None):
    """'mean' or 'mean ± std', with fewer decimals the larger the mean: 2 below 100, 1 below 1,000, else none."""
    digits = 2 if abs(mean) < 100 else 1 if abs(mean) < 1000 else 0
    text = f"{mean:,.{digits}f}"
    if std is not None:
        text += f" ± {std:,.{digits}f}"
    return text


def provenance(runs):
    """The lines every table carries: seeds, budget, commits, versions, machines."""

    def values(key):
        return "; ".join(sorted({r.meta.get(key, "not recorded") for r in runs}))

    steps = sorted({int(r.meta["global_step"]) for r in runs})
    wall = [float(r.meta["wall_time_s"]) for r in runs if "wall_time_s" in r.meta]
    return [
        f"- Seeds: {', '.join(map(str, sorted({r.seed for r in runs})))}; "
        f"{len(runs)} run{'s' if len(runs) > 1 else ''}.",
        f"- Budget: {', '.join(f'{s:,}' for s in steps)} environment steps per run.",
        f"- Commits: {values('commit')}.",
        f"- Versions: {values('versions')}.",
        f"- Machine: {values('machine')}.",
        *(
            [f"- Wall time: {sum(wall) / 3600:.1f} h in all, {statistics.mean(wall) / 60:.0f} min per run on average."]
            if wall
            else []
        ),
    ]


def suite_variants(suite):
    """The variants of a suite in the order suites.py defines them ([] for no suite of that name)."""
    return list(SUITES[suite].variants) if suite in SUITES else []


def suite_name(folder):
    """The run.py suite a results folder holds: 'shortfalls' for shortfalls/, 'table1' for table1_300k/; for a folder
    of no suite's name, the COLUMNS kind its name starts with, else 'mujoco'."""
    name = Path(folder).name
    default = next((kind for kind in COLUMNS if name.startswith(kind)), "mujoco")
    return max((k for k in SUITES if name == k or name.startswith(k + "_")), key=len, default=default)


def family(folder):
    """The module of reports/ that writes a results folder's report: the one its suite names."""
    return importlib.import_module(f"reports.{SUITES[suite_name(folder)].report}")


def readme_rel(folder, full):
    """The folder's path relative to the README that holds a block: benchmarks/README.md when `full`, else
    README.md at the root (the folder's name for a folder outside the repository)."""
    folder = Path(folder)
    return (
        folder.relative_to(ROOT / ("benchmarks" if full else "")).as_posix()
        if folder.is_relative_to(ROOT)
        else folder.name
    )


def ordered_variants(suite, runs):
    """The variants of the runs, in the order run.py defines them for `suite` (its default first)."""
    present = {r.variant for r in runs}
    return [v for v in suite_variants(suite) if v in present] + sorted(present - set(suite_variants(suite)))


def best_window(rows, window=100):
    """The best mean return of `window` consecutive episodes during training, and the step at which that window
    ends: beside the score (the last window), it shows a run that peaked and then fell back."""
    returns = [r[1] for r in rows]
    n = min(window, len(returns))
    means = [statistics.mean(returns[i - n : i]) for i in range(n, len(returns) + 1)]
    best = max(range(len(means)), key=means.__getitem__)
    return means[best], rows[best + n - 1][0]


def run_table(runs):
    """The table of every run: its steps, episodes, score, best 100 episodes, wall time, commit and beta range."""
    lines = [
        "| env | variant | seed | steps | episodes | score | best 100 episodes (at step) | wall time | commit"
        " | beta range |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(runs, key=lambda r: (r.env_id, r.variant, r.seed)):
        wall = f"{float(r.meta['wall_time_s']) / 60:.0f} min" if "wall_time_s" in r.meta else "–"
        best, at = best_window(r.rows)
        lines.append(
            f"| {r.env_id} | {r.variant} | {r.seed} | {int(r.meta['global_step']):,} | {len(r.rows)} | {fmt(r.score)}"
            f" | {fmt(best)} ({at:,}) | {wall} | {r.meta.get('commit', '–')} | {r.meta.get('beta_range', '–')} |"
        )
    return lines


def where_run(runs):
    """Where runs were made, from their CSVs: the torch threads their commands asked for, and the machines."""
    threads = sorted(
        {m.group(1) for r in runs if (m := re.search(r"--torch-threads (\d+)", r.meta.get("command", "")))}
    )
    machines = sorted({r.meta.get("machine", "an unrecorded machine") for r in runs})
    count = f"{' or '.join(threads)} torch thread{'s' if threads != ['1'] else ''}" if threads else "torch's threads"
    return f"{count} on {'; '.join(machines)}"


def curve(rows, grid, window=100):
    """The mean return of the last `window` episodes finished by each step of `grid` (nan before the first)."""
    import numpy as np

    steps = np.array([r[0] for r in rows], dtype=float)
    returns = np.array([r[1] for r in rows], dtype=float)
    csum = np.concatenate([[0.0], np.cumsum(returns)])
    out = np.full(len(grid), math.nan)
    for i, step in enumerate(grid):
        n = int(np.searchsorted(steps, step, side="right"))  # episodes finished by this step
        if n:
            k = min(window, n)
            out[i] = (csum[n] - csum[n - k]) / k
    return out


def save_figure(fig, folder, name, dpi=90):
    """Lay fig out, write it to folder/curves/name and close it; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out = Path(folder) / "curves" / name
    out.parent.mkdir(exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def plot_env(folder, env, runs, variants):
    """<folder>/curves/<env>.png: one line per variant, the mean over seeds with a ± std band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    total = max(int(r.meta["global_step"]) for r in runs)
    grid = np.linspace(0, total, 201)[1:]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    for variant in [v for v in variants if any(r.variant == v for r in runs)]:
        curves = np.array([curve(r.rows, grid) for r in runs if r.variant == variant])
        with warnings.catch_warnings():  # before any seed's first episode ends, the mean is nan
            warnings.simplefilter("ignore", RuntimeWarning)
            mean, std = np.nanmean(curves, axis=0), np.nanstd(curves, axis=0)
        label = f"{variant} ({len(curves)} seed{'s' if len(curves) > 1 else ''})"
        (line,) = ax.plot(grid, mean, label=label, lw=1.4)
        ax.fill_between(grid, mean - std, mean + std, color=line.get_color(), alpha=0.2, lw=0)
    ax.set_title(env)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("return, mean of last 100 episodes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return save_figure(fig, folder, f"{env.replace('/', '-')}.png")
