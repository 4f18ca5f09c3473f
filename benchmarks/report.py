"""Generate every benchmark table and learning-curve plot from the committed CSVs; nothing is typed.

    python benchmarks/report.py                  # every suite folder in benchmarks/results
    python benchmarks/report.py mujoco table1    # just these

For each suite folder that benchmarks/run.py filled (mujoco, table1, atari, or one of them at
another budget, such as table1_300k), it writes:
- <folder>/report.md: a run's score is the mean return of its last 100 episodes; a cell is the
  mean ± std (sample std) of the scores over seeds; beside ours, the published figures from
  benchmarks/reference_figures.csv. The table1 report also has the paper's normalized score.
- <folder>/curves/<env>.png: the mean ± std over seeds of the last-100-episode mean return
  against steps, one line per variant.

Table 1's normalized score, as the paper computes it: per env, the random policy scores 0 and
the best setting (the variant with the highest mean score over seeds) scores 1; each run's score
is mapped onto that scale, and a setting's figure is the mean over its runs. The random policy's
score is measured by benchmarks/random_score.py and read from results/random/<env>.csv.
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import statistics
import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from details import DETAILS_END, DETAILS_START, details_block  # noqa: E402

from common import load_script, replace_between  # noqa: E402
from results import RLHF_STATS, UPDATE_STATS, read_csv, score  # noqa: E402
from suites import (  # noqa: E402
    ATARI_NAMES,
    COLUMNS,
    FIGURE3_MISSING,
    FIGURE3_NAMES,
    README_ATARI_VARIANTS,
    SUITES,
    TABLE1_ENVS,
)

RESULTS = ROOT / "benchmarks" / "results"
REFERENCE = ROOT / "benchmarks" / "reference_figures.csv"


@dataclass
class Run:
    env_id: str
    variant: str
    seed: int
    rows: list  # (global_step, episodic_return, episodic_length)
    meta: dict

    @property
    def score(self):
        return score(self.rows)


def env_base(env_id):
    """'Hopper-v5' -> 'Hopper'; 'BreakoutNoFrameskip-v4' -> 'Breakout': the key of the reference figures."""
    return env_id.split("-v")[0].replace("NoFrameskip", "").removeprefix("ALE/")


SCORE_RULE = (
    "A run's score is the mean return of its last 100 episodes; a cell is the mean ± sample std over seeds,"
    " with the number of seeds in brackets."
)
MUJOCO_VERSIONS = (
    "Our MuJoCo tasks are gymnasium's -v5 where the env column does not name another version"
    " (the paper used gym's -v1, CleanRL -v4)."
)


def run_files(folder):
    """(env_id, variant, seed, path) for every <env>__<variant>__seed<N>.csv in a folder."""
    for path in sorted(Path(folder).glob("*__*__seed*.csv")):
        env_id, variant, seed = path.stem.split("__")
        yield env_id, variant, int(seed.removeprefix("seed")), path


def load_runs(folder):
    """Every run of a suite folder."""
    runs = []
    for env_id, variant, seed, path in run_files(folder):
        meta, rows = read_csv(path)
        runs.append(Run(env_id, variant, seed, rows, meta))
    return runs


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


def random_score(env_id, results=RESULTS):
    """The random policy's mean return on env_id, or None if random_score.py has not measured it."""
    path = Path(results) / "random" / f"{env_id.replace('/', '-')}.csv"
    if not path.exists():
        return None
    with open(path) as f:
        return statistics.mean(
            float(r["episodic_return"]) for r in csv.DictReader(line for line in f if not line.startswith("#"))
        )


def mean_std(values):
    """The mean, and the sample std (None for a single value, which has none)."""
    return statistics.mean(values), (statistics.stdev(values) if len(values) > 1 else None)


def group(runs):
    """{env_id: {variant: [run, ...]}}"""
    out = {}
    for run in runs:
        out.setdefault(run.env_id, {}).setdefault(run.variant, []).append(run)
    return out


def normalized_scores(runs, random):
    """Table 1's normalized score of each variant, over the envs every variant here was run on.

    runs: Run objects (or anything with env_id, variant and score); random: {env_id: score}.
    Returns ({variant: (mean, number of runs)}, the envs used, {env_id: best variant}).
    """
    by_env = group(runs)
    variants = sorted({run.variant for run in runs})
    envs = sorted(env for env, row in by_env.items() if all(v in row for v in variants) and random.get(env) is not None)
    best_of = {env: max(variants, key=lambda v: statistics.mean(r.score for r in by_env[env][v])) for env in envs}
    pooled = {
        v: [x for xs in per_env.values() for x in xs]
        for v, per_env in normalized_runs(runs, random, envs, best_of).items()
    }
    return {v: (statistics.mean(s), len(s)) for v, s in pooled.items()}, envs, best_of


def normalized_runs(runs, random, envs, best_of):
    """{variant: {env: [the normalized score of each of its runs there]}}: on each env the random policy scores 0
    and the mean of its best variant, best_of[env], scores 1."""
    by_env, out = group(runs), {}
    for env in envs:
        lo, hi = random[env], statistics.mean(r.score for r in by_env[env][best_of[env]])
        for variant, variant_runs in by_env[env].items():
            out.setdefault(variant, {})[env] = [(r.score - lo) / (hi - lo) for r in variant_runs]
    return out


def normalized_by_env(runs, random, envs, best_of):
    """{variant: {env: (mean normalized score of its runs there, number of runs)}}, scaled as in normalized_scores."""
    per_run = normalized_runs(runs, random, envs, best_of)
    return {v: {env: (statistics.mean(xs), len(xs)) for env, xs in per_env.items()} for v, per_env in per_run.items()}


def standard_errors(runs, random, envs, best_of):
    """{variant: the standard error over seeds of its normalized score}, for the variants with 2+ runs on every env.

    The score is the mean of N = sum of n_e runs, n_e on env e, whose scores vary by s_e² from seed to seed there; its
    variance is sum(n_e s_e²) / N². The envs themselves are fixed, and so is each env's scale (its best variant's mean).
    """
    out = {}
    for v, per_env in normalized_runs(runs, random, envs, best_of).items():
        if all(len(xs) > 1 for xs in per_env.values()):
            out[v] = math.sqrt(sum(len(xs) * statistics.variance(xs) for xs in per_env.values())) / sum(
                map(len, per_env.values())
            )
    return out


def complete(runs, rows):
    """Whether every row has run on every env and every seed that any of the runs has."""
    have = {(r.variant, r.env_id, r.seed) for r in runs}
    return all((v, e, s) in have for v in rows for e in {r.env_id for r in runs} for s in {r.seed for r in runs})


def verdict(norm, rows, se=None):
    """Whether the paper's order holds in our normalized scores (Table 1: clip 0.2 best, no clipping worst,
    adaptive KL below clipping), in words computed from the scores; None if a row has no score.

    se: {row: standard error}. Each comparison then gives its gap ± the gap's standard error, and says when the gap
    is within twice that: the seeds run cannot tell the two rows apart.
    """
    if any(row not in norm for row in rows):
        return None
    score, se = {row: norm[row][0] for row in rows}, se or {}
    best, worst = max(score, key=score.get), min(score, key=score.get)
    kl = [row for row in rows if row.startswith("kl")]
    best_kl = max(kl, key=score.get)
    runner_up = max((row for row in rows if row != "clip0.2"), key=score.get)
    second_worst = min((row for row in rows if row != "no-clip"), key=score.get)
    noise = []

    def gap(a, b):
        """How far row a is above row b, with the gap's standard error where both rows have one."""
        d = score[a] - score[b]
        if a not in se or b not in se:
            return f"by {d:.2f}"
        e = math.hypot(se[a], se[b])
        noise.append(abs(d) <= 2 * e)
        return f"by {d:.2f} ± {e:.2f}" + (" (within 2 standard errors)" if noise[-1] else "")

    parts = [
        f"clip 0.2 is the best of the 11 rows, ahead of {runner_up} {gap('clip0.2', runner_up)}"
        if best == "clip0.2"
        else (
            f"clip 0.2 ({score['clip0.2']:.2f}) is not the best row: "
            f"{best} is ({score[best]:.2f}), ahead {gap(best, 'clip0.2')}"
        ),
        f"no clipping or penalty is the worst, behind {second_worst} {gap(second_worst, 'no-clip')}"
        if worst == "no-clip"
        else (
            f"no clipping ({score['no-clip']:.2f}) is not the worst row: "
            f"{worst} is ({score[worst]:.2f}), behind it {gap('no-clip', worst)}"
        ),
        (
            "every adaptive KL row is below clip 0.2: "
            f"the best, {best_kl} ({score[best_kl]:.2f}), is behind it {gap('clip0.2', best_kl)}"
        )
        if score[best_kl] < score["clip0.2"]
        else (
            f"adaptive KL {best_kl} ({score[best_kl]:.2f}) is not below clip 0.2 ({score['clip0.2']:.2f}): "
            f"it is ahead {gap(best_kl, 'clip0.2')}"
        ),
    ]
    holds = best == "clip0.2" and worst == "no-clip" and score[best_kl] < score["clip0.2"]
    text = (
        f"**The paper's order {'holds' if holds else 'does not hold'} here, in the mean scores:** "
        + "; ".join(parts)
        + "."
    )
    if noise:  # a gap has a standard error
        text += " ± is the standard error over seeds" + (
            "; a gap within twice it is one these seeds cannot settle." if any(noise) else "."
        )
    return text


def fmt(mean, std=None):
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


def suite_variants(kind):
    """The variants of a suite in the order run.py defines them."""
    return list(SUITES[kind].variants) if kind in SUITES else []


def suite_name(folder):
    """The run.py suite a results folder holds: 'shortfalls' for shortfalls/, 'table1' for table1_300k/."""
    name = Path(folder).name
    return max((k for k in SUITES if name == k or name.startswith(k + "_")), key=len, default=suite_kind(folder))


def ordered_variants(suite, runs):
    """The variants of the runs, in the order run.py defines them for `suite` (its default first)."""
    present = {r.variant for r in runs}
    return [v for v in suite_variants(suite) if v in present] + sorted(present - set(suite_variants(suite)))


def score_table(runs, reference, columns, variants, results):
    """env rows; a column of ours per variant, the random policy, then the reference columns."""
    by_env = group(runs)
    head = [f"ours: {v} (n)" for v in variants] + ["random policy"] + [title for _, title, _ in columns]
    lines = ["| env | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for env in sorted(by_env):
        cells = []
        for v in variants:
            scores = [r.score for r in by_env[env].get(v, [])]
            cells.append(f"{fmt(*mean_std(scores))} ({len(scores)})" if scores else "–")
        rand = random_score(env, results)
        cells.append(fmt(rand) if rand is not None else "not measured")
        for column, _, setting in columns:
            ref = reference.get((column, env_base(env), setting))
            cells.append(fmt(ref[0], ref[1]) if ref else "–")
        lines.append(f"| {env} | " + " | ".join(cells) + " |")
    return lines


def best_window(rows, window=100):
    """The best mean return of `window` consecutive episodes during training, and the step at which that window
    ends: beside the score (the last window), it shows a run that peaked and then fell back."""
    returns = [r[1] for r in rows]
    n = min(window, len(returns))
    means = [statistics.mean(returns[i - n : i]) for i in range(n, len(returns) + 1)]
    best = max(range(len(means)), key=means.__getitem__)
    return means[best], rows[best + n - 1][0]


def run_table(runs):
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


def sources(reference, columns):
    lines = []
    for column, title, _ in columns:
        srcs = list(dict.fromkeys(src for (c, _, _), (_, _, src) in reference.items() if c == column))
        lines.append(f"- {title}: {srcs[0]}" if srcs else f"- {title}: no figures")
    return lines


def suite_kind(folder):
    """mujoco, table1 or atari, from the folder's name (table1_300k is a table1)."""
    return next((k for k in COLUMNS if Path(folder).name.startswith(k)), "mujoco")


def tables(folder, runs, reference, results, level="##"):
    """The tables of a suite: Table 1's normalized score (for table1), then the scores per env."""
    kind, variants = suite_kind(folder), ordered_variants(suite_name(folder), runs)
    lines = []
    if kind == "table1":
        envs = sorted({r.env_id for r in runs})
        random = {env: random_score(env, results) for env in envs}
        norm, norm_envs, best_of = normalized_scores(runs, random)
        errors = standard_errors(runs, random, norm_envs, best_of)
        lines += [
            f"{level} Normalized score (the paper's Table 1)",
            "",
            f"Variants run: {', '.join(variants)}. Envs where all of them ran: {', '.join(norm_envs) or 'none'}.",
            "Per env the random policy scores 0 and the best of the variants *run here* scores 1; the paper",
            "took the best of all 11 of its settings, so where fewer are run here the best is easier to be,",
            "and the figures are comparable with the paper's in their order more than in their values.",
            "A score is shown ± its standard error over seeds where every env has 2 or more runs"
            " (the paper gives none).",
            "",
            "| setting | ours: normalized score | runs | paper, Table 1 |",
            "|---|---|---|---|",
        ]
        for v in suite_variants("table1"):  # every row of the paper's table, run here or not
            paper = reference.get(("paper_table1", "", v))
            ours = norm.get(v)
            n = sum(r.variant == v for r in runs)
            missing = "not run" if not n else f"not on every env yet ({n} run{'s' if n > 1 else ''})"
            ours_text = ours and f"{ours[0]:.2f}" + (f" ± {errors[v]:.2f}" if v in errors else "")
            lines.append(
                f"| {v} | {ours_text} | {ours[1]} | {paper[0]:.2f} |"
                if ours
                else f"| {v} | {missing} | – | {paper[0]:.2f} |"
            )
        rows = suite_variants("table1")
        text = (
            verdict(norm, rows, errors) if complete(runs, rows) else None
        )  # not on a partial grid, whose scores rest on fewer envs or seeds
        grid = len(rows) * len(envs) * len({r.seed for r in runs})
        over = (
            ""
            if set(norm_envs) == set(envs)
            else (
                f" Until then the scores are over {', '.join(norm_envs) or 'no env'},"
                " where every row run so far has run."
            )
        )
        lines += [
            "",
            text
            or (
                "The verdict on the paper's order (clip 0.2 best, no clipping worst, adaptive KL below clipping)"
                f" waits for all 11 rows on every env and seed: {sum(r.variant in rows for r in runs)} of {grid} runs"
                f" are in.{over}"
            ),
        ]
        by_env = normalized_by_env(runs, random, norm_envs, best_of) if norm_envs else {}
        lines += (
            []
            if not by_env
            else [
                "",
                "Per env (normalized score, runs), and the commits each setting's runs were made at:",
                "",
                "| setting | " + " | ".join(norm_envs) + " | commits |",
                "|---" * (len(norm_envs) + 2) + "|",
            ]
        )
        for v in [v for v in suite_variants("table1") if v in by_env]:
            commits = ", ".join(sorted({r.meta.get("commit", "?") for r in runs if r.variant == v}))
            cells = [f"{by_env[v][env][0]:.2f} ({by_env[v][env][1]})" if env in by_env[v] else "–" for env in norm_envs]
            lines.append(f"| {v} | " + " | ".join(cells) + f" | {commits} |")
        if norm_envs:
            lines += ["", "| env | best variant here |", "|---|---|"]
            lines += [f"| {env} | {best_of[env]} |" for env in norm_envs]
        lines += ["", f"{level} Scores", ""]
    if kind == "atari":
        return lines + atari_table(runs, reference, variants, results) + atari_comparison(runs, variants)
    if kind == "humanoid":  # §6.3: both metrics, as for Figure 3, beside the published figures
        return lines + humanoid_table(runs, reference, variants, results)
    lines += score_table(runs, reference, COLUMNS[kind], variants, results)
    if (
        kind == "mujoco" and len(variants) > 1
    ):  # a suite that tests changes against a default: shortfalls, beta_collapse
        lines += comparison(runs, reference, variants)
    return lines


def difference(scores, base_scores):
    """The difference of the mean scores, scores minus base_scores, and its standard error over seeds,
    sqrt(s1²/n1 + s2²/n2); None unless both sides have 2 or more seeds."""
    if len(scores) < 2 or len(base_scores) < 2:
        return None
    d = statistics.mean(scores) - statistics.mean(base_scores)
    return d, math.sqrt(statistics.variance(scores) / len(scores) + statistics.variance(base_scores) / len(base_scores))


def fmt_difference(scores, base_scores):
    """'+d ± se' from difference(), in bold where the difference exceeds 2 standard errors; '–' where it has none."""
    diff = difference(scores, base_scores)
    if diff is None:
        return "–"
    d, se = diff
    return f"**{d:+,.1f} ± {se:,.1f}**" if abs(d) > 2 * se else f"{d:+,.1f} ± {se:,.1f}"


def comparison(runs, reference, variants):
    """Each setting against the first (the suite's default) on the env's newest version, per env: the difference of
    the mean scores with its standard error, and whether the setting reaches the paper's figure. An older version of
    an env (IDP-v4 beside IDP-v5) is compared with the same default on the newest."""
    base, by_env = variants[0], group(runs)
    lines = [
        "",
        f"Against `{base}` on the env's newest version: the difference of the mean scores ± its standard error,"
        " sqrt(s1²/n1 + s2²/n2); **bold** where the difference is more than twice that. With 3 seeds a side this is"
        " a rough guide, not a test.",
        "",
        f"| env | setting | score (n) | difference from {base} | reaches the paper's Fig. 3 (clip 0.2, approx.) |",
        "|---|---|---|---|---|",
    ]
    for name in sorted({env_base(env) for env in by_env}):
        envs = sorted(
            (env for env in by_env if env_base(env) == name), key=lambda env: int(env.rsplit("-v", 1)[1]), reverse=True
        )
        paper = reference.get(("paper_fig3", name, "clip0.2"))
        base_scores = [r.score for r in by_env[envs[0]].get(base, [])]
        for env in envs:
            for v in [v for v in variants if v in by_env[env]]:
                scores = [r.score for r in by_env[env][v]]
                diff = "–" if (env, v) == (envs[0], base) else fmt_difference(scores, base_scores)
                reached = (
                    "–" if not paper else f"{'yes' if statistics.mean(scores) >= paper[0] else 'no'} ({fmt(paper[0])})"
                )
                lines.append(f"| {env} | {v} | {fmt(*mean_std(scores))} ({len(scores)}) | {diff} | {reached} |")
    return lines


def humanoid_table(runs, reference, variants, results):
    """Per variant, the mean ± std over seeds of the last 100 episodes and of every episode of training; then the
    random policy and the published figures for PPO on gymnasium's Humanoid, each at its own budget and settings."""
    by_env = group(runs)
    lines = ["| env | setting | steps | last 100 (n) | all training (n) |", "|---|---|---|---|---|"]
    for env in sorted(by_env):
        for v in [v for v in variants if v in by_env[env]]:
            last = [r.score for r in by_env[env][v]]
            whole = [mean_return(r.rows) for r in by_env[env][v]]
            steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in by_env[env][v]}))
            n = len(last)
            lines.append(f"| {env} | {v} | {steps} | {fmt(*mean_std(last))} ({n}) | {fmt(*mean_std(whole))} ({n}) |")
        rand = random_score(env, results)
        lines += ["", f"The random policy on {env}: {fmt(rand) if rand is not None else 'not measured'}."]
        for column, title, setting in COLUMNS["humanoid"]:
            ref = reference.get((column, env_base(env), setting))
            lines.append(f"- {title}: {fmt(ref[0], ref[1]) if ref else '–'}")
    return lines


def mean_return(rows):
    """The paper's other Atari metric (§6.4): the mean score of every episode of training."""
    return statistics.mean(r for _, r, _ in rows)


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
    the arm is ahead or behind by more than 2 standard errors, or within them (issue 30)."""
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


def report(folder, reference=None, results=RESULTS):
    """Write <folder>/report.md and <folder>/curves/*.png; return the markdown."""
    folder = Path(folder)
    runs = load_runs(folder)
    if not runs:
        raise ValueError(f"{folder} has no run CSVs")
    if suite_name(folder) == "rlhf":
        return rlhf_report(folder, runs)
    if suite_name(folder) == "figure3":
        text = figure3_markdown(folder, results)
        (folder / "report.md").write_text(text)
        return text
    reference = reference if reference is not None else load_reference()
    kind = suite_kind(folder)
    variants = ordered_variants(suite_name(folder), runs)
    lines = [
        f"# {folder.name}: scores",
        "",
        "Generated by `benchmarks/report.py` from the CSVs in this folder; do not edit by hand.",
        SCORE_RULE + ("" if kind == "atari" else " " + MUJOCO_VERSIONS),
        "",
        *provenance(runs),
        "",
        *tables(folder, runs, reference, results),
        "",
        "Sources of the published figures:",
        *sources(reference, COLUMNS[kind] + ([("paper_table1", "paper, Table 1", "")] if kind == "table1" else [])),
        "",
        "## Learning curves",
        "",
    ]
    for env in sorted({r.env_id for r in runs}):
        png = plot_env(folder, env, [r for r in runs if r.env_id == env], variants)
        lines.append(f"![{env}](curves/{png.name})")
    lines += video_section(folder)
    lines += beta_section(folder)
    if (
        kind == "mujoco" and len(suite_variants(suite_name(folder))) > 1
    ):  # the suites that look for a cause: shortfalls, beta_collapse
        lines += updates_section(folder, variants)
    lines += ["", "## Every run", "", *run_table(runs)]
    text = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(text)
    return text


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
            cells = [f"{fmt(*mean_std(last))} ({len(last)})", f"{fmt(*mean_std(whole))} ({len(whole)})"]
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


def save_figure(fig, folder, name, dpi=90):
    """Lay fig out, write it to folder/curves/name and close it; returns the path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out = Path(folder) / "curves" / name
    out.parent.mkdir(exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


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


# ppo_rlhf.py's suite: what its table shows of each run, the mean over the last tenth of its iterations.
RLHF_COLUMNS = [
    ("score", "RM score"),
    ("gold_score", "gold score"),
    ("kl", "KL to pi_SFT (nats)"),
    ("entropy", "entropy"),
    ("well_formed", "well formed"),
    ("spam", "spam"),
    ("garbled", "garbled"),
    ("eos_fraction", "ends in EOS"),
    ("response_length", "length"),
    ("rm_accuracy", "RM accuracy on the policy's pool"),
]
BEST_OF_N = ("n", "kl", "score", "gold_score", "well_formed", "spam", "garbled", "rm_accuracy")  # best_of_n.py's CSV
BLIND_SPOT = (
    "The spam rule is a blind spot planted in the reward model's data: π_SFT never says a clause twice, so no pair it"
    " learned from ranks a repeat."
)


def read_rlhf_series(folder):
    """{(variant, seed): numpy array [iterations, 1 + len(RLHF_STATS)]} from <folder>/rlhf/, which run.py writes."""
    import numpy as np

    return {
        (variant, seed): np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        for _, variant, seed, path in run_files(Path(folder) / "rlhf")
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


def falls(series):
    """{(variant, seed): text} for each run over-optimized (Gao et al. 2022): its gold score, per tenth of training,
    ended more than 10% below its peak while its KL to pi_SFT grew past its value there and its RM score ended at
    least as high; the text names the hack by the larger of the spam and garbled shares of the last tenth."""
    out = {}
    for key, run in sorted(series.items()):
        gold, score, kl = (tenths(run, name) for name in ("gold_score", "score", "kl"))
        peak = max(range(len(gold)), key=gold.__getitem__)
        if gold[-1] < gold[peak] - 0.1 * abs(gold[peak]) and kl[-1] > kl[peak] and score[-1] >= score[peak]:
            spam, garbled = tenths(run, "spam")[-1], tenths(run, "garbled")[-1]
            hack = f"spam {spam:.2f}" if spam >= garbled else f"garbled {garbled:.2f}"
            if max(spam, garbled) < 0.1:
                hack = f"well-formed text the RM overrates (spam {spam:.2f}, garbled {garbled:.2f})"
            out[key] = f"gold {gold[peak]:.1f} to {gold[-1]:.1f} as KL grew {kl[peak]:.1f} to {kl[-1]:.1f}; {hack}"
    return out


def best_of_n_lines(best):
    """report.md's table of best-of-N from pi_SFT: per N, each metric's mean ± std over the seeds' reward models."""
    import numpy as np

    names = [(n, h) for n, h in RLHF_COLUMNS if n in BEST_OF_N[2:-1]]
    names = [("kl", "KL to pi_SFT (nats, analytic)"), *names, ("rm_accuracy", "RM accuracy on the kept responses")]
    lines = ["| N | " + " | ".join(heading for _, heading in names) + " |", "|---" * (len(names) + 1) + "|"]
    tables = [table for _, table in best.values()]
    for i, n in enumerate(tables[0][:, 0]):
        cells = []
        for name, _ in names:
            values = [t[i, BEST_OF_N.index(name)] for t in tables if not np.isnan(t[i, BEST_OF_N.index(name)])]
            cells.append(f"{fmt(*mean_std(values))} ({len(values)})" if values else "–")
        lines.append(f"| {n:.0f} | " + " | ".join(cells) + " |")
    return lines


def rlhf_report(folder, runs):
    """<folder>/report.md for the rlhf suite: per setting, each metric's mean over the last tenth of the iterations,
    then the mean ± std over seeds, and per seed; best-of-N from pi_SFT; <folder>/curves/reviews.png: the RM score and
    the gold score against sqrt(KL) over training, as Gao et al. (2022) plot over-optimization, with best-of-N's
    frontier; and the responses each run printed last."""
    series = read_rlhf_series(folder)
    best = read_best_of_n(folder)
    variants = ordered_variants("rlhf", runs)
    header = "| setting | " + " | ".join(heading for _, heading in RLHF_COLUMNS) + " | RM accuracy, pi_SFT's pairs |"
    lines = [f"# {folder.name}: RLHF on the review language", "", "Generated by `benchmarks/report.py`.", ""]
    lines += [*provenance(runs), "", header, "|---" * (len(RLHF_COLUMNS) + 2) + "|"]
    for variant in variants:
        runs_of = [series[key] for key in sorted(series) if key[0] == variant]
        cells = []
        for name, _ in RLHF_COLUMNS:
            last = [tenths(s, name)[-1] for s in runs_of]
            cells.append(f"{fmt(*mean_std(last))} ({len(last)})")
        held_out = [float(r.meta["rm_held_out_accuracy"]) for r in runs if r.variant == variant]
        cells.append(f"{fmt(*mean_std(held_out))} ({len(held_out)})" if held_out else "–")
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Each run's mean over the last tenth of training, as the mean ± std over seeds (n). The reward model's accuracy"
        " is the share of pairs of responses with different gold scores that it ranks as gold does: on a pool of the"
        " policy's responses, the first 16 of every rollout so far, and on held-out pairs of pi_SFT's responses to one"
        " prompt, of the kind it was trained on. Spam says a clause twice; garbled text is outside the grammar.",
        "",
        "Per seed, at the end of training (the means of its last tenth; the pool's pairs at the end):",
        "",
        "| setting | seed | RM score | gold score | KL to pi_SFT (nats) | RM accuracy, held out | RM accuracy, pool"
        " (pairs) | spam | garbled | over-optimized |",
        "|---" * 10 + "|",
    ]
    fell = falls(series)
    held_out = {r.seed: float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta}
    for variant in variants:
        for seed in sorted(seed for v, seed in series if v == variant):
            run = series[(variant, seed)]
            cells = [f"{tenths(run, name)[-1]:.2f}" for name in ("score", "gold_score", "kl")]
            cells.append(f"{held_out[seed]:.2f}" if seed in held_out else "–")
            pairs = run[-1, 1 + RLHF_STATS.index("rm_pairs")]
            cells.append(f"{tenths(run, 'rm_accuracy')[-1]:.2f} ({pairs:,.0f})")
            cells += [f"{tenths(run, name)[-1]:.2f}" for name in ("spam", "garbled")]
            cells.append(fell.get((variant, seed), "no"))
            lines.append(f"| {variant} | {seed} | " + " | ".join(cells) + " |")
    lines += ["", BLIND_SPOT]
    if best:
        meta = [m for m, _ in best.values()]
        wall = sum(float(m.get("wall_time_s", 0)) for m in meta)
        lines += [
            "",
            f"## Best-of-N from pi_SFT (seeds {', '.join(map(str, sorted(best)))})",
            "",
            "For each of 256 prompts, N responses of pi_SFT, and the one the seed's reward model scores highest kept:"
            " the frontier of gold against KL that needs no optimizer, with KL[best-of-N || pi_SFT] = log N - (N - 1)"
            f" / N (`benchmarks/best_of_n.py`; commits {'; '.join(sorted({m.get('commit', '?') for m in meta}))};"
            f" {wall / 60:.1f} min in all).",
            "",
            *best_of_n_lines(best),
        ]
    lines += [
        "",
        "![RM and gold score against sqrt(KL)](curves/reviews.png)",
        "",
        "Per seed, the gold score (solid, left axis) and the RM's score (dashed, right axis) against sqrt(KL), each a"
        " moving average over 10 iterations, with the gold score's peak marked:",
        "",
        "![per seed](curves/seeds.png)",
        "",
        "## The responses the reward model scored highest, last printed",
        "",
    ]
    for variant in variants:
        for seed in sorted(seed for v, seed in series if v == variant):
            path = folder / "samples" / f"reviews__{variant}__seed{seed}.txt"
            text = path.read_text().strip() if path.exists() else "(none kept)"
            lines += [f"{variant}, seed {seed}:", "", "```", text, "```", ""]
    plot_rlhf(folder, series, variants, best)
    plot_rlhf_seeds(folder, series, variants)
    text = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(text)
    return text


def plot_rlhf(folder, series, variants, best=None):
    """<folder>/curves/reviews.png: per setting, the mean over seeds of the RM and gold scores against sqrt(KL); and
    best-of-N's, N = 1 ... 64, at its analytic KL."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), sharex=True)
    for variant in variants:
        runs_of = [series[key] for key in sorted(series) if key[0] == variant]
        n = min(len(s) for s in runs_of)
        mean = np.mean([s[:n] for s in runs_of], axis=0)
        x = np.sqrt(np.clip(mean[:, 1 + RLHF_STATS.index("kl")], 0, None))
        for ax, name in zip(axes, ("score", "gold_score"), strict=True):
            ax.plot(x, mean[:, 1 + RLHF_STATS.index(name)], label=f"{variant} ({len(runs_of)})", lw=1.2)
    if best:
        mean = np.mean([table for _, table in best.values()], axis=0)
        for ax, name in zip(axes, ("score", "gold_score"), strict=True):
            label = f"best-of-N, N = 1 ... {mean[-1, 0]:.0f} ({len(best)})"
            ax.plot(np.sqrt(mean[:, 1]), mean[:, BEST_OF_N.index(name)], "k--o", ms=3, lw=1, label=label)
    for ax, title in zip(axes, ("reward model's score", "gold score"), strict=True):
        ax.set_title(title)
        ax.set_xlabel("sqrt(KL[pi || pi_SFT]), nats^0.5")
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7)
    return save_figure(fig, folder, "reviews.png")


def moving_average(x, width=10):
    """The mean of each window of `width` iterations, one per iteration from the width-th on."""
    import numpy as np

    return np.convolve(x, np.ones(width) / width, mode="valid")


def plot_rlhf_seeds(folder, series, variants):
    """<folder>/curves/seeds.png: a panel per setting and seed, the gold score and the RM's score against sqrt(KL)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    seeds = sorted({seed for _, seed in series})
    fig, axes = plt.subplots(len(variants), len(seeds), figsize=(3.2 * len(seeds), 2.2 * len(variants)), squeeze=False)
    for row, variant in enumerate(variants):
        for col, seed in enumerate(seeds):
            ax = axes[row][col]
            ax.set_title(f"{variant}, seed {seed}", fontsize=8)
            if (variant, seed) not in series:
                ax.axis("off")
                continue
            run = series[(variant, seed)]
            x = moving_average(np.sqrt(np.clip(run[:, 1 + RLHF_STATS.index("kl")], 0, None)))
            gold = moving_average(run[:, 1 + RLHF_STATS.index("gold_score")])
            ax.plot(x, gold, color="C1", lw=1)
            peak = int(np.argmax(gold))
            ax.plot(x[peak], gold[peak], "v", color="C1", ms=6)
            ax.set_ylabel("gold", fontsize=7, color="C1")
            rm = ax.twinx()
            rm.plot(x, moving_average(run[:, 1 + RLHF_STATS.index("score")]), color="C0", lw=1, ls="--")
            rm.set_ylabel("RM score", fontsize=7, color="C0")
            for a in (ax, rm):
                a.tick_params(labelsize=6)
            ax.grid(alpha=0.3)
            if row == len(variants) - 1:
                ax.set_xlabel("sqrt(KL[pi || pi_SFT])", fontsize=7)
    return save_figure(fig, folder, "seeds.png", dpi=80)


RLHF_START = "<!-- rlhf: generated by benchmarks/report.py from benchmarks/results/rlhf; do not edit by hand -->"
RLHF_END = "<!-- end of rlhf -->"


def tenths(run, name):
    """The mean of a run's rlhf/<name> over each tenth of its iterations, in order, counted from the end: the last
    is the mean of the last tenth, as in report.md."""
    import numpy as np

    column = run[:, 1 + RLHF_STATS.index(name)]
    width = max(1, len(column) // 10)
    first = len(column) % width
    with warnings.catch_warnings():  # an iteration with no pair of different gold has no RM accuracy: nan
        warnings.simplefilter("ignore", RuntimeWarning)
        return [np.nanmean(column[i : i + width]) for i in range(first, len(column), width)]


def where_run(runs):
    """Where runs were made, from their CSVs: the torch threads their commands asked for, and the machines."""
    threads = sorted(
        {m.group(1) for r in runs if (m := re.search(r"--torch-threads (\d+)", r.meta.get("command", "")))}
    )
    machines = sorted({r.meta.get("machine", "an unrecorded machine") for r in runs})
    count = f"{' or '.join(threads)} torch thread{'s' if threads != ['1'] else ''}" if threads else "torch's threads"
    return f"{count} on {'; '.join(machines)}"


def rlhf_block(results=RESULTS):
    """The README's RLHF results: the suite's table in short, what a default run took here, and what the runs say
    about the KL penalty: whether gold fell while the reward model's score held or rose, and the controller's KL."""
    folder = Path(results) / "rlhf"
    runs = load_runs(folder) if folder.is_dir() else []
    if not runs:
        return "\n".join([RLHF_START, "No run of the rlhf suite is committed yet.", RLHF_END])
    finished = {(r.variant, r.seed) for r in runs}
    series = {key: s for key, s in read_rlhf_series(folder).items() if key in finished}
    variants = ordered_variants("rlhf", runs)
    seeds = ", ".join(map(str, sorted({r.seed for r in runs})))
    steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in runs}))
    columns = [c for c in RLHF_COLUMNS if c[0] in ("score", "gold_score", "kl", "entropy", "spam", "garbled")]
    columns.append(("rm_accuracy", "RM accuracy, the policy's pool"))
    lines = [
        RLHF_START,
        "",
        f"**`rlhf`: {len(runs)} runs (seeds {seeds}; {steps} responses each)**"
        " ([report, plot and samples](benchmarks/results/rlhf/report.md)): each run's mean over the last tenth of"
        " training, as the mean ± std over seeds:",
        "",
        "| setting | " + " | ".join(heading for _, heading in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    last = {}
    for variant in variants:
        runs_of = {seed: series[(v, seed)] for v, seed in sorted(series) if v == variant}
        last[variant] = {name: [tenths(s, name)[-1] for s in runs_of.values()] for name in RLHF_STATS}
        cells = [fmt(*mean_std(last[variant][name])) for name, _ in columns]
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    script = load_script("ppo_rlhf.py").Args()
    # The suite's variant with no flags of its own, at the script's default budget, is `python ppo_rlhf.py`.
    plain = [v for v, (_, flags) in SUITES["rlhf"].variants.items() if not flags]
    default_runs = [r for r in runs if r.variant in plain and int(r.meta["global_step"]) == script.total_episodes]
    minutes = sorted(float(r.meta["wall_time_s"]) / 60 for r in default_runs)
    lines.append("")
    if minutes:
        lines.append(
            f"- **Time.** A default run, `python ppo_rlhf.py`, took {minutes[0]:.1f}–{minutes[-1]:.1f} min for all"
            f" three stages, with {where_run(default_runs)} ({len(minutes)} run{'s' if len(minutes) > 1 else ''};"
            " other work may have shared it)."
        )
    # Stages 1 and 2 depend only on the seed: one reward model a seed, whichever setting ran it.
    held_out = {r.seed: float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta}
    if held_out:
        lines.append(
            f"- **The reward model** ranked {fmt(*mean_std(list(held_out.values())))} of held-out pairs of π_SFT's"
            f" responses as gold does ({len(held_out)} seeds, one reward model each); the table's last column is its"
            " accuracy on a pool of the policy's own responses, where the policy went."
        )
    fell, overoptimized = falls(series), []
    for variant in variants:
        texts = [f"seed {seed}: {text}" for (v, seed), text in fell.items() if v == variant]
        detail = f" ({'; '.join(texts)})" if texts else ""
        overoptimized.append(f"{variant} {len(texts)} of {len(last[variant]['score'])}{detail}")
    lines.append(
        "- **Over-optimization** (Gao et al. 2022). Seeds whose gold score, per tenth of training, ended more than 10%"
        " below its peak while the KL to π_SFT grew past its value there and the RM score ended at least as high, with"
        " the hack that the last tenth shows most: " + ", ".join(overoptimized) + f". {BLIND_SPOT}"
    )
    best = read_best_of_n(folder)
    if best:
        import numpy as np

        mean = np.mean([table for _, table in best.values()], axis=0)
        gold, kl = mean[:, BEST_OF_N.index("gold_score")], mean[:, BEST_OF_N.index("kl")]
        lines.append(
            f"- **Best-of-N** from π_SFT, the frontier no optimizer is needed for, reached gold {gold[-1]:.2f} at N ="
            f" {mean[-1, 0]:.0f} (KL {kl[-1]:.2f} nats, analytic; {gold[0]:.2f} at N = 1), with the reward models"
            f" of seeds {', '.join(map(str, sorted(best)))}."
        )
    adaptive = [v for v, (_, flags) in SUITES["rlhf"].variants.items() if flags == ["--adaptive-kl"] and v in last]
    for variant in adaptive:
        lines.append(
            f"- **The controller** held the KL over the last tenth of training at {fmt(*mean_std(last[variant]['kl']))}"
            f" nats, for a target of {script.kl_target:g}, with β there at {fmt(*mean_std(last[variant]['kl_coef']))}."
        )
    return "\n".join(lines + ["", RLHF_END])


README_START = "<!-- results: generated by benchmarks/report.py from the CSVs; do not edit by hand -->"
README_END = "<!-- end of results -->"


def readme_block(results=RESULTS, reference=None, full=False):
    """A README's Results block, from the same CSVs as report.md: the full tables and curves of every
    suite (for benchmarks/README.md), or a short summary of the suites at their own budgets (README.md)."""
    reference = reference if reference is not None else load_reference()
    results = Path(results)
    lines = [README_START, "", f"{SCORE_RULE} {MUJOCO_VERSIONS}"]
    for folder in suite_folders(results):
        if suite_name(folder) == "rlhf":  # not a table of returns: its report.md has its own
            continue
        if suite_name(folder) == "figure3":  # PPO against its peers: the verdict and the figure, the tables in full
            lines += figure3_block(folder, results, full)
            continue
        runs = load_runs(folder)
        if not full and suite_kind(folder) == "atari":  # ours and the peer; the single arms: the report
            runs = [r for r in runs if r.variant in README_ATARI_VARIANTS]
        # Links are relative to the README that holds the block: README.md at the root, benchmarks/README.md.
        rel = (
            folder.relative_to(ROOT / ("benchmarks" if full else "")).as_posix()
            if folder.is_relative_to(ROOT)
            else folder.name
        )
        seeds = ", ".join(map(str, sorted({r.seed for r in runs})))
        steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in runs}))
        heading = f"`{folder.name}`: {len(runs)} run{'s' if len(runs) > 1 else ''} (seeds {seeds}; {steps} steps each)"
        if full:
            lines += [
                "",
                f"### {heading}",
                "",
                f"Commits, versions, machine, each run's score and the sources: [`{rel}/report.md`]({rel}/report.md).",
                "",
                *tables(folder, runs, reference, results, level="####"),
                "",
                " ".join(
                    f'<img src="{rel}/curves/{env.replace("/", "-")}.png" width="32%">'
                    for env in sorted({r.env_id for r in runs})
                ),
            ]
        elif folder.name in COLUMNS:  # the short summary: each suite at its own budget, one table each
            kind = suite_kind(folder)
            table = tables(folder, runs, reference, results, level="####")
            if kind == "table1":  # just the normalized score, the paper's Table 1, and the verdict on its order
                table = table[table.index("| setting | ours: normalized score | runs | paper, Table 1 |") :]
                table = table[: table.index("") + 2]
            comparison = [i for i, line in enumerate(table) if line.startswith("Each arm against")]
            if comparison:  # the arms' differences from the default: in report.md and benchmarks/README.md only
                table = table[: comparison[0] - 1]
            lines += ["", f"**{heading}** ([report]({rel}/report.md))", "", *table]
            frames = sorted((folder / "video").glob("*.png"))  # a frame of the trained policy's video
            lines += (
                ["", " ".join(f'<img src="{rel}/video/{frame.name}" width="32%">' for frame in frames)]
                if frames
                else []
            )
    return "\n".join(lines + ["", README_END])


def figure3_block(folder, results, full):
    """The README's lines on the paper's Figure 3: the verdict and the figure; in full, the tables too."""
    rel = (
        folder.relative_to(ROOT / ("benchmarks" if full else "")).as_posix()
        if folder.is_relative_to(ROOT)
        else folder.name
    )
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


COST_START = "<!-- cost: generated by benchmarks/report.py from the runs' wall times; do not edit by hand -->"
COST_END = "<!-- end of cost -->"


def cost_block(results=RESULTS):
    """What the full Table 1 costs, from the wall time of the 1M-step MuJoCo runs made here (each on one core)."""
    from run import make_grid

    runs = [
        r
        for folder in ("mujoco", "table1")
        if (Path(results) / folder).is_dir()
        for r in load_runs(Path(results) / folder)
    ]
    minutes = [float(r.meta["wall_time_s"]) / 60 for r in runs if "wall_time_s" in r.meta]
    full = make_grid("table1", results_root=results)  # the paper's 7 envs
    ours = make_grid("table1", envs=TABLE1_ENVS, results_root=results)
    lines = [COST_START, ""]
    if minutes:
        per_run = statistics.mean(minutes)
        todo = sum(not job.csv.exists() for job in ours)
        lines += [
            f"A 1M-step MuJoCo run took {per_run:.0f} min of wall time on one core here, on average over"
            f" {len(minutes)} runs. Table 1 as the paper ran it, {len(full)} runs"
            f" ({len(SUITES['table1'].variants)} rows x 7 envs x 3 seeds), is then about"
            f" {len(full) * per_run / 60:.0f} CPU-hours; on our 4 envs ({', '.join(TABLE1_ENVS)}) it is"
            f" {len(ours)} runs, about {len(ours) * per_run / 60:.0f} CPU-hours, "
            + (
                f"of which {todo} run{'s are' if todo > 1 else ' is'} not done yet"
                f" ({todo * per_run / 60:.0f} CPU-hours)."
                if todo
                else "all of them done."
            )
        ]
    return "\n".join(lines + ["", COST_END])


QUICK_START = (
    "<!-- quick start: generated by benchmarks/report.py from benchmarks/results/mujoco; do not edit by hand -->"
)
QUICK_END = "<!-- end of quick start -->"


def quickstart_block(results=RESULTS):
    """What the README's quick start promises (how long `python ppo_continuous.py` takes and where it ends),
    from the mujoco suite's Hopper-v5 runs: the same script, env, budget and settings."""
    folder = Path(results) / "mujoco"
    runs = (
        [r for r in load_runs(folder) if r.env_id == "Hopper-v5" and r.variant == "clip0.2"] if folder.is_dir() else []
    )
    minutes = sorted(float(r.meta["wall_time_s"]) / 60 for r in runs if "wall_time_s" in r.meta)
    scores = sorted(r.score for r in runs)
    if not (runs and minutes):
        return "\n".join([QUICK_START, "- **Training**: no benchmark run of Hopper-v5 is committed yet.", QUICK_END])
    line = (
        f"- **Training** took {minutes[0]:.0f}–{minutes[-1]:.0f} min per run for the benchmarks,"
        f" with {where_run(runs)}, and ended with a mean return of {scores[0]:,.0f}–{scores[-1]:,.0f}"
        " over the last 100 episodes"
        f" ({len(runs)} seeds; see [Results](#results))."
    )
    return "\n".join([QUICK_START, line, QUICK_END])


def update_readme(path, block, start=README_START, end=README_END):
    text = replace_between(Path(path).read_text(), start, end, block)
    if text is None:
        raise ValueError(f"{path} has no markers ({start} ... {end})")
    Path(path).write_text(text)


def suite_folders(results=RESULTS):
    """The folders with run CSVs: the mujoco suites first, then table1, then atari."""
    folders = [p for p in Path(results).iterdir() if p.is_dir() and any(run_files(p))]
    return sorted(folders, key=lambda p: (list(COLUMNS).index(suite_kind(p)), p.name))


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


def video_section(folder):
    """The trained policy, filmed by ppo_continuous.py --eval-checkpoint --capture-video: a frame and the video."""
    videos = sorted((Path(folder) / "video").glob("*.mp4"))
    if not videos:
        return []
    lines = ["", "## The trained policy", ""]
    for video in videos:
        if video.with_suffix(".png").exists():
            lines += [f"[![{video.stem}](video/{video.stem}.png)](video/{video.name})", ""]
        lines += [f"[video/{video.name}](video/{video.name}): {video.stem.replace('__', ', ')}", ""]
    return lines


def read_beta(folder):
    """{(env_id, variant, seed): [(step, beta, kl), ...]} from <folder>/beta/, which run.py writes for KL runs."""
    out = {}
    for env_id, variant, seed, path in run_files(Path(folder) / "beta"):
        with open(path) as f:
            out[env_id, variant, seed] = [
                (int(r["global_step"]), float(r["beta"]), float(r["kl"])) for r in csv.DictReader(f)
            ]
    return out


def kl_targets(runs):
    """{(env_id, variant, seed): d_targ} for the adaptive-KL runs among `runs`, from each run's command."""
    out, default = {}, None
    for run in runs:
        words = run.meta.get("command", "").split()
        if "ppo_kl_penalty.py" in words and "--no-adaptive-beta" not in words:
            if "--kl-target" in words:
                out[run.env_id, run.variant, run.seed] = float(words[words.index("--kl-target") + 1])
            else:  # the script's own default, read from it
                default = default or load_script("ppo_kl_penalty.py").Args().kl_target
                out[run.env_id, run.variant, run.seed] = default
    return out


def beta_section(folder):
    """For the adaptive-KL rows: beta over training, per env, and how it ends (the last 10% of updates)."""
    runs = {(r.env_id, r.variant, r.seed): r for r in load_runs(folder)}
    targets = kl_targets(runs.values())
    series = {key: rows for key, rows in read_beta(folder).items() if key in targets}
    if not series:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [
        "",
        "## Beta over training (adaptive KL)",
        "",
        "From the beta each update used (`losses/beta`). The rule halves beta after each update whose KL is below",
        "d_targ / 1.5. As the learning rate anneals linearly to 0, the last updates are too small to reach that,",
        "and beta halves again and again: the halvings column counts the halvings in a row that end each run.",
        "The last two columns bound what the last 10% of the steps did to the score: the mean return of the last",
        "100 episodes at 90% of the steps, and at the end (the run's score), averaged over the seeds.",
        "",
        "| env | setting | seeds | median beta, first 90% of updates | beta at the end"
        " | updates in the last 10% with KL < d_targ / 1.5 | final run of updates with KL < d_targ / 1.5"
        " | score at 90% of the steps | score at the end |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for env in sorted({key[0] for key in series}):
        fig, ax = plt.subplots(figsize=(6, 3.4))
        for (e, variant, seed), rows in sorted(series.items()):
            if e == env:
                ax.plot([r[0] for r in rows], [r[1] for r in rows], lw=1, label=f"{variant} seed {seed}")
        ax.set_yscale("log")
        ax.set_title(f"{env}: beta of the adaptive KL penalty")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("beta")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        save_figure(fig, folder, f"beta-{env}.png")
        for variant in sorted({key[1] for key in series if key[0] == env}):
            keys = [key for key in sorted(series) if key[:2] == (env, variant)]
            betas, low_kl = [series[key] for key in keys], [targets[key] / 1.5 for key in keys]
            cut = [int(0.9 * len(rows)) for rows in betas]
            early = statistics.mean(
                statistics.median(r[1] for r in rows[:c]) for rows, c in zip(betas, cut, strict=True)
            )
            end = statistics.mean(rows[-1][1] for rows in betas)
            low = statistics.mean(
                statistics.mean(r[2] < kl for r in rows[c:]) for rows, c, kl in zip(betas, cut, low_kl, strict=True)
            )
            streak = [
                next((i for i, r in enumerate(reversed(rows)) if r[2] >= kl), len(rows))
                for rows, kl in zip(betas, low_kl, strict=True)
            ]
            before = statistics.mean(
                curve(runs[key].rows, [0.9 * int(runs[key].meta["global_step"])])[0] for key in keys
            )
            after = statistics.mean(runs[key].score for key in keys)
            lines.append(
                f"| {env} | {variant} | {len(keys)} | {early:.3g} | {end:.3g} | {low:.0%}"
                f" | {', '.join(map(str, streak))} | {fmt(before)} | {fmt(after)} |"
            )
    lines += [""] + [f"![beta, {env}](curves/beta-{env}.png)" for env in sorted({key[0] for key in series})]
    return lines


def updates_section(folder, variants):
    """The update's statistics over training, per env and setting: each run's mean over each tenth of its
    updates, averaged over the seeds, under the return at the end of each tenth. From <folder>/updates/,
    which run.py writes for every run."""
    runs = {(r.env_id, r.variant, r.seed): r for r in load_runs(folder)}
    stats = {}
    for env_id, variant, seed, path in run_files(Path(folder) / "updates"):
        with open(path) as f:
            rows = [[float(x) for x in row.values()] for row in csv.DictReader(f)]
        if len(rows) >= 10 and (env_id, variant, seed) in runs:
            stats.setdefault((env_id, variant), []).append((runs[env_id, variant, seed], rows))
    if not stats:
        return []
    lines = [
        "",
        "## The updates over training",
        "",
        "The return (the mean of the last 100 episodes) at the end of each tenth of the steps, and under it each",
        "update's statistics as the script logs them (`losses/*`, see the README's Logged metrics) averaged over",
        "that tenth of the updates; each the mean over the seeds (their number in brackets). An explained variance",
        "below 0 means that the value function predicts the batch's returns worse than their mean does, so that the",
        "advantages are mostly its error.",
        "",
        "| env | setting | statistic | " + " | ".join(f"{10 * i}–{10 * i + 10}%" for i in range(10)) + " |",
        "|---" * 13 + "|",
    ]
    order = {v: i for i, v in enumerate(variants)}
    for env, variant in sorted(stats, key=lambda key: (key[0], order.get(key[1], len(order)), key[1])):
        pairs = stats[env, variant]
        returns = [
            statistics.mean(curve(run.rows, [int(run.meta["global_step"]) * (i + 1) / 10])[0] for run, _ in pairs)
            for i in range(10)
        ]
        lines.append(f"| {env} | {variant} ({len(pairs)}) | return | " + " | ".join(fmt(x) for x in returns) + " |")
        for j, name in enumerate(UPDATE_STATS, start=1):
            tenths = [
                statistics.mean(
                    statistics.mean(r[j] for r in rows[len(rows) * i // 10 : len(rows) * (i + 1) // 10])
                    for _, rows in pairs
                )
                for i in range(10)
            ]
            lines.append(
                f"| {env} | {variant} ({len(pairs)}) | {name} | " + " | ".join(f"{x:.3g}" for x in tenths) + " |"
            )
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "suites", nargs="*", help="suite folders under benchmarks/results (default: every one with run CSVs)"
    )
    parser.add_argument("--results-dir", type=Path, default=RESULTS)
    args = parser.parse_args()
    folders = [args.results_dir / s for s in args.suites] or suite_folders(args.results_dir)
    for folder in folders:
        if not folder.is_dir():
            sys.exit(f"report.py: error: no folder {folder}")
        try:
            report(folder, results=args.results_dir)
        except ValueError as e:
            sys.exit(f"report.py: error: {e}")
        print(f"wrote {folder / 'report.md'} and {folder / 'curves'}/")
    if args.results_dir.resolve() == RESULTS:
        update_readme(ROOT / "README.md", readme_block())
        update_readme(ROOT / "README.md", quickstart_block(), QUICK_START, QUICK_END)
        update_readme(ROOT / "benchmarks" / "README.md", readme_block(full=True))
        update_readme(ROOT / "benchmarks" / "README.md", cost_block(), COST_START, COST_END)
        update_readme(ROOT / "README.md", details_block(), DETAILS_START, DETAILS_END)
        update_readme(ROOT / "README.md", rlhf_block(), RLHF_START, RLHF_END)
        print("updated the Results blocks of README.md and benchmarks/README.md")


if __name__ == "__main__":
    main()
