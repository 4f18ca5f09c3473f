"""The humanoid family: the paper's §6.3 showcase, both of its metrics beside the random policy and the published
figures for PPO on gymnasium's Humanoid."""

from __future__ import annotations

from reports import scores
from reports.base import MUJOCO_VERSIONS, SCORE_RULE, env_base, fmt, ordered_variants, suite_name
from reports.stats import group, mean_return, mean_std
from results import load_runs, random_score
from suites import COLUMNS

ORDER = 2  # where its suites stand in the READMEs' Results block: by ORDER, then by folder name


def tables(folder, runs, reference, results, level="##"):
    """Both metrics per setting, as for Figure 3, beside the published figures (humanoid_table)."""
    return humanoid_table(runs, reference, ordered_variants(suite_name(folder), runs), results)


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves; returns the markdown."""
    rule = f"{SCORE_RULE} {MUJOCO_VERSIONS}"
    return scores.write_report(folder, runs, reference, results, tables, rule, COLUMNS["humanoid"])


def readme_lines(folder, results, reference, full):
    """The suite's lines in a README's Results block (scores.readme_lines)."""
    return scores.readme_lines(folder, load_runs(folder), results, reference, full, tables)


def humanoid_table(runs, reference, variants, results):
    """Per variant, the mean ± std over seeds of the last 100 episodes and of every episode of training, and the wall
    time of a run (table4-2ranks: the same run in 2 processes under torchrun); then the random policy and the published
    figures for PPO on gymnasium's Humanoid, each at its own budget and settings."""
    by_env = group(runs)
    lines = [
        "| env | setting | steps | last 100 (n) | all training (n) | wall time per run |",
        "|---|---|---|---|---|---|",
    ]
    for env in sorted(by_env):
        for v in [v for v in variants if v in by_env[env]]:
            last = [r.score for r in by_env[env][v]]
            whole = [mean_return(r.rows) for r in by_env[env][v]]
            steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in by_env[env][v]}))
            n = len(last)
            wall = ", ".join(f"{float(r.meta['wall_time_s']) / 60:.0f} min" for r in by_env[env][v])
            lines.append(
                f"| {env} | {v} | {steps} | {fmt(*mean_std(last))} ({n}) | {fmt(*mean_std(whole))} ({n}) | {wall} |"
            )
        rand = random_score(env, results)
        lines += ["", f"The random policy on {env}: {fmt(rand) if rand is not None else 'not measured'}."]
        for column, title, setting in COLUMNS["humanoid"]:
            ref = reference.get((column, env_base(env), setting))
            lines.append(f"- {title}: {fmt(ref[0], ref[1]) if ref else '–'}")
    return lines
