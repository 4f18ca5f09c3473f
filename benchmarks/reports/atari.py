"""The atari family: both of the paper's Atari metrics (§6.4) per game and setting, beside the random policy and the
published figures at ten times our budget, and each arm against today's defaults."""

from __future__ import annotations

import statistics

from reports import scores
from reports.base import SCORE_RULE, env_base, fmt, ordered_variants, suite_name
from reports.stats import difference, fmt_difference, group, mean_return, mean_std
from results import load_runs, random_score
from suites import ATARI_NAMES, COLUMNS, README_ATARI_VARIANTS

ORDER = 3  # where its suites stand in the READMEs' Results block: by ORDER, then by folder name


def tables(folder, runs, reference, results, level="##"):
    """Both metrics per game and setting, then each arm against the defaults."""
    variants = ordered_variants(suite_name(folder), runs)
    return atari_table(runs, reference, variants, results) + atari_comparison(runs, variants)


def summary(folder, runs, reference, results):
    """The README's short table: both metrics per game, without the arms' differences (report.md has them)."""
    return atari_table(runs, reference, ordered_variants(suite_name(folder), runs), results)


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves; returns the markdown."""
    return scores.write_report(folder, runs, reference, results, tables, SCORE_RULE, COLUMNS["atari"])


def readme_lines(folder, results, reference, full):
    """The suite's lines in a README's Results block (scores.readme_lines); in short, ours at the defaults, ours with
    the RL Zoo's settings and the peer (README_ATARI_VARIANTS): the single arms are in the report."""
    runs = load_runs(folder)
    if not full:
        runs = [r for r in runs if r.variant in README_ATARI_VARIANTS]
    return scores.readme_lines(folder, runs, results, reference, full, tables, summary)


def atari_table(runs, reference, variants, results):
    """Per game, both of the paper's Atari metrics (§6.4) for each variant, one row each, as mean ± std over seeds
    of the raw game score: the mean over all of training (which rewards fast learning) and over the last 100
    episodes; and on a game's first row, the random policy and the published figures, at ten times our budget."""
    by_env = group(runs)
    head = ["setting", "all training (n)", "last 100 (n)", "random policy"] + [t for _, t, _ in COLUMNS["atari"]]
    lines = ["| game | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for env in sorted(by_env):
        rand = random_score(env, results)
        refs = [fmt(rand) if rand is not None else "not measured"]
        for column, _, setting in COLUMNS["atari"]:
            ref = reference.get((column, env_base(env), setting))
            refs.append(fmt(ref[0], ref[1]) if ref else "–")
        for i, v in enumerate(v for v in variants if v in by_env[env]):
            cells = [ATARI_NAMES.get(v, v)]
            for metric in (lambda r: mean_return(r.rows), lambda r: r.score):
                values = [metric(r) for r in by_env[env][v]]
                cells.append(f"{fmt(*mean_std(values))} ({len(values)})")
            cells += refs if i == 0 else [""] * len(refs)  # the game's references once, on its first row
            lines.append(f"| {env} | " + " | ".join(cells) + " |")
    walls = []
    for v in variants:
        wall = [float(r.meta["wall_time_s"]) for r in runs if r.variant == v and "wall_time_s" in r.meta]
        if wall:
            plural = "s" if len(wall) > 1 else ""
            walls.append(f"{ATARI_NAMES.get(v, v)}: {statistics.mean(wall) / 60:.0f} min ({len(wall)} run{plural})")
    gpu = (
        "The paper's budget, 10M steps, on a GPU (not yet tested on one here):"
        " `python ppo_atari.py --env-id BreakoutNoFrameskip-v4 --device cuda --compile`."
    )
    timing = f"Wall time per run here, on average (other work may have shared the machine): {'; '.join(walls)}. "
    lines += ["", f"- {timing if walls else ''}{gpu}"]
    return lines


def atari_comparison(runs, variants, base="ppo"):
    """Each arm against today's defaults (`base`), per game and on both of the paper's Atari metrics: the difference
    of the mean scores and its standard error over seeds (difference(), as the shortfalls suites have it), and whether
    the arm is ahead or behind by more than 2 standard errors, or within them."""
    by_env = group(runs)
    arms = [v for v in variants if v != base]
    if base not in variants or not arms:
        return []
    lines = [
        "",
        f"Each arm against `{base}` ({ATARI_NAMES[base]}, at today's defaults), per game: the difference of the mean"
        " scores ± its standard error over seeds, sqrt(s1²/n1 + s2²/n2); **bold** where the difference exceeds 2"
        " standard errors, and only then does the verdict call the arm ahead or behind. A difference needs 2 or more"
        " seeds a side. With 3 seeds a side this is a rough guide, not a test.",
        "",
        f"| game | arm | last 100 (n) | difference from {base}: last 100 | difference from {base}: all training"
        " | verdict (last 100) |",
        "|---|---|---|---|---|---|",
    ]
    for env in sorted(by_env):
        base_runs = by_env[env].get(base, [])
        for v in [v for v in arms if v in by_env[env]]:
            arm_runs = by_env[env][v]
            last = [r.score for r in arm_runs]
            diff = difference(last, [r.score for r in base_runs])
            if diff is None:
                words = "fewer than 2 seeds a side"
            elif abs(diff[0]) > 2 * diff[1]:
                words = f"{'ahead of' if diff[0] > 0 else 'behind'} {base} by more than 2 standard errors"
            else:
                words = "within 2 standard errors"
            cells = [
                f"{fmt(*mean_std(last))} ({len(last)})",
                fmt_difference(last, [r.score for r in base_runs]),
                fmt_difference([mean_return(r.rows) for r in arm_runs], [mean_return(r.rows) for r in base_runs]),
                words,
            ]
            lines.append(f"| {env} | {ATARI_NAMES.get(v, v)} | " + " | ".join(cells) + " |")
    return lines
