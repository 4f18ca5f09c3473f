"""The humanoid family: the paper's §6.3 showcase, both of its metrics beside the random policy and the published
figures for PPO on gymnasium's Humanoid."""

from __future__ import annotations

from reports import scores
from reports.base import MUJOCO_VERSIONS, SCORE_RULE, env_base, fmt, ordered_variants, suite_name
from reports.stats import difference, group, mean_return, mean_std, welch
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
            lines.append("| " + " | ".join([env, v, *score_cells(by_env[env][v])]) + " |")
        lines += welch_line(by_env[env])
        rand = random_score(env, results)
        lines += ["", f"The random policy on {env}: {fmt(rand) if rand is not None else 'not measured'}."]
        for column, title, setting in COLUMNS["humanoid"]:
            ref = reference.get((column, env_base(env), setting))
            lines.append(f"- {title}: {fmt(ref[0], ref[1]) if ref else '–'}")
    return lines


def score_cells(runs):
    """A setting's cells: its runs' steps, the mean ± std over seeds of the last 100 episodes and of every episode of
    training, and each run's wall time."""
    last = [r.score for r in runs]
    whole = [mean_return(r.rows) for r in runs]
    steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in runs}))
    wall = ", ".join(f"{float(r.meta['wall_time_s']) / 60:.0f} min" for r in runs)
    return [steps, f"{fmt(*mean_std(last))} ({len(last)})", f"{fmt(*mean_std(whole))} ({len(whole)})", wall]


def welch_line(by_variant, variant="table4-2ranks", base="table4"):
    """The same run in 2 processes against one: Welch's t-test of their last-100 scores over seeds."""
    if variant not in by_variant or base not in by_variant:
        return []
    scores, base_scores = [r.score for r in by_variant[variant]], [r.score for r in by_variant[base]]
    test = welch(scores, base_scores)
    if test is None:
        return []
    d, se = difference(scores, base_scores)
    t, df, p = test
    beyond = "beyond" if abs(d) > 2 * se else "within"
    return [
        "",
        f"{variant} minus {base}, last 100 episodes: {d:+,.0f} ± {se:,.0f} (standard error; {beyond} 2 of them);"
        f" Welch's t = {t:.2f} on {df:.1f} degrees of freedom, two-sided p = {p:.2f}"
        f" ({len(scores)} and {len(base_scores)} seeds).",
    ]
