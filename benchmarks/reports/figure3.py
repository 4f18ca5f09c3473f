"""The figure3 family: the paper's Figure 3, PPO (the mujoco suite's runs at ppo_continuous.py's defaults) against
SB3's A2C and sb3-contrib's TRPO (the figure3 suite's runs): a verdict per peer, both metrics per task, the figure, and
which RL Zoo entry each peer ran with."""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

from reports.base import (
    MUJOCO_VERSIONS,
    SCORE_RULE,
    curve,
    env_base,
    fmt,
    provenance,
    readme_rel,
    run_table,
    save_figure,
)
from reports.stats import difference, fmt_difference, group, mean_return, mean_std
from results import RESULTS, load_runs
from suites import FIGURE3_MISSING, FIGURE3_NAMES, SUITES

ORDER = 0  # where its suites stand in the READMEs' Results block: by ORDER, then by folder name


def figure3_runs(folder, results=RESULTS):
    """The peers' runs in `folder`, and PPO's: the mujoco suite's runs of ppo_continuous.py at its defaults."""
    mujoco = Path(results) / "mujoco"
    ppo = [replace(r, variant="ppo") for r in load_runs(mujoco) if r.variant == "clip0.2"] if mujoco.is_dir() else []
    tasks = set(SUITES["figure3"].envs) | {r.env_id for r in load_runs(folder)}
    return [r for r in ppo if r.env_id in tasks] + load_runs(folder)


def figure3_verdict(runs, names=True):
    """Per peer, the tasks on which PPO is ahead by more than 2 standard errors over the last 100 episodes, behind
    by more than 2, within 2, or not yet comparable (fewer than 2 seeds a side): a line of words, which names the
    tasks unless `names` is false (the README's short line)."""
    by_env, parts = group(runs), []
    for peer in [v for v in FIGURE3_NAMES if v != "ppo" and any(r.variant == v for r in runs)]:
        counts = {"ahead": [], "behind": [], "within 2 standard errors": [], "not comparable yet": []}
        for env in sorted(by_env):
            diff = difference(
                [r.score for r in by_env[env].get("ppo", [])], [r.score for r in by_env[env].get(peer, [])]
            )
            key = "not comparable yet" if diff is None else "within 2 standard errors"
            if diff is not None and abs(diff[0]) > 2 * diff[1]:
                key = "ahead" if diff[0] > 0 else "behind"
            counts[key].append(env_base(env))
        named = {key: f" ({', '.join(envs)})" if names else "" for key, envs in counts.items()}
        words = [f"{key} on {len(envs)}{named[key]}" for key, envs in counts.items() if envs]
        parts.append(f"against {FIGURE3_NAMES[peer]}, PPO is " + ("; " if names else ", ").join(words))
    if not names:
        return f"over the last 100 episodes of {len(by_env)} tasks, " + "; ".join(parts) + "."
    return (
        f"**Over the last 100 episodes, of {len(by_env)} tasks:** " + ". And ".join(parts) + "."
        " Ahead or behind means by more than 2 standard errors of the difference, sqrt(s1²/n1 + s2²/n2); a task is"
        " not comparable until both sides have 2 seeds."
    )


def figure3_tables(runs, level="##"):
    """Per task, each algorithm's two scores (the paper's two metrics) and PPO's difference from each peer."""
    by_env = group(runs)
    lines = [
        f"{level} Scores per task",
        "",
        "Each algorithm's mean ± std over seeds (n) of the mean return of the last 100 episodes, and of every"
        " episode of training; PPO's difference from each peer ± its standard error, **bold** beyond 2.",
        "",
        "| task | algorithm | last 100 (n) | all training (n) | PPO minus it: last 100 | PPO minus it: all training |",
        "|---|---|---|---|---|---|",
    ]
    for env in sorted(by_env):
        ppo = by_env[env].get("ppo", [])
        for variant in [v for v in FIGURE3_NAMES if v in by_env[env]]:
            these = by_env[env][variant]
            last, whole = [r.score for r in these], [mean_return(r.rows) for r in these]
            cells = [
                f"{fmt(*mean_std(last))} ({len(last)})",
                f"{fmt(*mean_std(whole))} ({len(whole)})",
            ]
            if variant == "ppo":
                cells += ["", ""]
            else:
                cells += [
                    fmt_difference([r.score for r in ppo], last),
                    fmt_difference([mean_return(r.rows) for r in ppo], whole),
                ]
            lines.append(f"| {env} | {FIGURE3_NAMES[variant]} | " + " | ".join(cells) + " |")
    return lines


def figure3_sources(runs):
    """Which RL Zoo entry each peer ran with, per task, from its CSVs' headers."""
    lines = ["| task | " + " | ".join(FIGURE3_NAMES[v] for v in ("a2c", "trpo")) + " |", "|---|---|---|"]
    for env in sorted({r.env_id for r in runs}):
        cells = []
        for variant in ("a2c", "trpo"):
            found = sorted(
                {r.meta.get("hyperparameters", "not recorded") for r in runs if (r.env_id, r.variant) == (env, variant)}
            )
            cells.append("; ".join(found) or "not run yet")
        lines.append(f"| {env} | " + " | ".join(cells) + " |")
    return lines


def figure3_markdown(folder, results=RESULTS):
    """<folder>/report.md of the figure3 suite, with <folder>/curves/figure3.png drawn beside it."""
    runs = figure3_runs(folder, results)
    peers = [r for r in runs if r.variant != "ppo"]
    plot_figure3(folder, runs)
    lines = [
        f"# {folder.name}: the paper's Figure 3, PPO against A2C and TRPO",
        "",
        "Generated by `benchmarks/report.py` from the CSVs in this folder and PPO's in `../mujoco/`; do not edit by"
        " hand.",
        SCORE_RULE + " " + MUJOCO_VERSIONS,
        "",
        "The peers (`benchmarks/sb3_mujoco.py`):",
        *provenance(peers),
        "",
        "PPO (`ppo_continuous.py` at its defaults, the mujoco suite's runs):",
        *provenance([r for r in runs if r.variant == "ppo"]),
        "",
        figure3_verdict(runs),
        "",
        "![Figure 3](curves/figure3.png)",
        "",
        *figure3_tables(runs),
        "",
        "## The peers' hyperparameters",
        "",
        "Each peer runs with the RL Zoo's hyperparameters for its algorithm and task, read from the rl_zoo3 package's"
        " own files; the Zoo tuned its MuJoCo entries on gym's -v4 tasks, and a -v5 task takes its -v4 entry. Where"
        " the Zoo has no entry, its `default` entry: SB3's defaults.",
        "",
        *figure3_sources(peers),
        "",
        FIGURE3_MISSING,
        "",
        "## Every run",
        "",
        *run_table(runs),
    ]
    return "\n".join(lines) + "\n"


def plot_figure3(folder, runs):
    """<folder>/curves/figure3.png laid out as the paper's Figure 3: a panel per task, the mean over seeds of the
    last-100-episode return against steps, each algorithm a line with a ± std band, the x axis to 1M."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    envs = sorted({r.env_id for r in runs})
    cols = 4
    fig, axes = plt.subplots(
        math.ceil(len(envs) / cols), cols, figsize=(3.3 * cols, 2.7 * math.ceil(len(envs) / cols)), squeeze=False
    )
    total = max(int(r.meta["global_step"]) for r in runs)
    grid = np.linspace(0, total, 101)[1:]
    for ax, env in zip(axes.flat, envs, strict=False):
        for color, variant in enumerate(FIGURE3_NAMES):  # one color an algorithm, in every panel
            if not any((r.env_id, r.variant) == (env, variant) for r in runs):
                continue
            curves = np.array([curve(r.rows, grid) for r in runs if (r.env_id, r.variant) == (env, variant)])
            with warnings.catch_warnings():  # before any seed's first episode ends, the mean is nan
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, std = np.nanmean(curves, axis=0), np.nanstd(curves, axis=0)
            ax.plot(grid, mean, lw=1.2, color=f"C{color}", label=f"{FIGURE3_NAMES[variant]} ({len(curves)})")
            ax.fill_between(grid, mean - std, mean + std, color=f"C{color}", alpha=0.2, lw=0)
        ax.set_title(env, fontsize=9)
        ax.set_xlim(0, total)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="best")
    for ax in list(axes.flat)[len(envs) :]:
        ax.axis("off")
    fig.supxlabel("environment steps", fontsize=8)
    fig.supylabel("return, mean of last 100 episodes", fontsize=8)
    return save_figure(fig, folder, "figure3.png")


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and <folder>/curves/figure3.png; returns the markdown."""
    text = figure3_markdown(folder, results)
    (Path(folder) / "report.md").write_text(text)
    return text


def readme_lines(folder, results, reference, full):
    """The README's lines on the paper's Figure 3: the verdict and the figure; in full, the tables too."""
    rel = readme_rel(folder, full)
    runs = figure3_runs(folder, results)
    peers = [r for r in runs if r.variant != "ppo"]
    seeds = ", ".join(map(str, sorted({r.seed for r in peers})))
    count = f"{len(peers)} peer run{'s' if len(peers) != 1 else ''}"
    heading = f"`{folder.name}`: PPO against A2C and TRPO, the paper's Figure 3 ({count}, seeds {seeds})"
    if full:
        lines = ["", f"### {heading}", "", f"[report]({rel}/report.md). {figure3_verdict(runs)}"]
    else:
        lines = ["", f"**{heading}** ([report]({rel}/report.md)): {figure3_verdict(runs, names=False)}"]
    lines += ["", f'<img src="{rel}/curves/figure3.png" width="{100 if full else 80}%">']
    return lines + (["", *figure3_tables(runs, level="####"), "", FIGURE3_MISSING] if full else [])
