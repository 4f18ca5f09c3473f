"""The table1 family: the paper's Table 1, its normalized score per setting with a standard error over seeds and the
verdict on the paper's order, then the scores per env; and what the full table costs, for benchmarks/README.md.

Table 1's normalized score, as the paper computes it: per env, the random policy scores 0 and the best setting (the
variant with the highest mean score over seeds) scores 1; each run's score is mapped onto that scale, and a setting's
figure is the mean over its runs. The random policy's score is measured by benchmarks/random_score.py and read from
results/random/<env>.csv.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path

from reports import scores
from reports.base import MUJOCO_VERSIONS, SCORE_RULE, ordered_variants, suite_name, suite_variants
from reports.stats import group
from results import RESULTS, load_runs, random_score
from suites import COLUMNS, SUITES, TABLE1_ENVS

ORDER = 1  # where its suites stand in the READMEs' Results block: by ORDER, then by folder name
# The published figures its report cites: the per-env columns, and the paper's Table 1 itself.
SOURCES = COLUMNS["table1"] + [("paper_table1", "paper, Table 1", "")]


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


@dataclass
class Normalized:
    """Table 1's normalized scores of a folder's runs, and what they rest on."""

    scores: dict  # {variant: (mean normalized score, number of runs)}
    envs: list  # the envs every variant run here has run on (and the random policy has been measured on)
    best_of: dict  # {env: its best variant, which scores 1 there}
    errors: dict  # {variant: standard error over seeds}, for the variants with 2+ runs on every env
    by_env: dict  # {variant: {env: (mean normalized score, number of runs)}}


def normalize(runs, results):
    """The Normalized scores of `runs`, with the random policy's scores from `results`."""
    random = {env: random_score(env, results) for env in sorted({r.env_id for r in runs})}
    norm, envs, best_of = normalized_scores(runs, random)
    errors = standard_errors(runs, random, envs, best_of)
    by_env = normalized_by_env(runs, random, envs, best_of) if envs else {}
    return Normalized(norm, envs, best_of, errors, by_env)


def normalized_table(runs, reference, norm):
    """The paper's Table 1 beside ours: a row per setting of the paper, run here or not."""
    lines = ["| setting | ours: normalized score | runs | paper, Table 1 |", "|---|---|---|---|"]
    for v in suite_variants("table1"):  # every row of the paper's table, run here or not
        paper = reference.get(("paper_table1", "", v))
        ours = norm.scores.get(v)
        n = sum(r.variant == v for r in runs)
        missing = "not run" if not n else f"not on every env yet ({n} run{'s' if n > 1 else ''})"
        ours_text = ours and f"{ours[0]:.2f}" + (f" ± {norm.errors[v]:.2f}" if v in norm.errors else "")
        lines.append(
            f"| {v} | {ours_text} | {ours[1]} | {paper[0]:.2f} |"
            if ours
            else f"| {v} | {missing} | – | {paper[0]:.2f} |"
        )
    return lines


def verdict_text(runs, norm):
    """The verdict on the paper's order, or what it waits for: it is not given on a partial grid, whose scores rest
    on fewer envs or seeds."""
    rows = suite_variants("table1")
    text = verdict(norm.scores, rows, norm.errors) if complete(runs, rows) else None
    if text:
        return text
    envs = sorted({r.env_id for r in runs})
    grid = len(rows) * len(envs) * len({r.seed for r in runs})
    over = (
        ""
        if set(norm.envs) == set(envs)
        else f" Until then the scores are over {', '.join(norm.envs) or 'no env'}, where every row run so far has run."
    )
    return (
        "The verdict on the paper's order (clip 0.2 best, no clipping worst, adaptive KL below clipping)"
        f" waits for all 11 rows on every env and seed: {sum(r.variant in rows for r in runs)} of {grid} runs"
        f" are in.{over}"
    )


def per_env_lines(runs, norm):
    """Each setting's normalized score per env with the commits its runs were made at, and each env's best setting."""
    if not norm.by_env:
        return []
    lines = [
        "",
        "Per env (normalized score, runs), and the commits each setting's runs were made at:",
        "",
        "| setting | " + " | ".join(norm.envs) + " | commits |",
        "|---" * (len(norm.envs) + 2) + "|",
    ]
    for v in [v for v in suite_variants("table1") if v in norm.by_env]:
        commits = ", ".join(sorted({r.meta.get("commit", "?") for r in runs if r.variant == v}))
        cells = [
            f"{norm.by_env[v][env][0]:.2f} ({norm.by_env[v][env][1]})" if env in norm.by_env[v] else "–"
            for env in norm.envs
        ]
        lines.append(f"| {v} | " + " | ".join(cells) + f" | {commits} |")
    lines += ["", "| env | best variant here |", "|---|---|"]
    return lines + [f"| {env} | {norm.best_of[env]} |" for env in norm.envs]


def tables(folder, runs, reference, results, level="##"):
    """Table 1's normalized score with the verdict and the per-env figures, then the scores per env."""
    norm = normalize(runs, results)
    variants = ordered_variants(suite_name(folder), runs)
    return [
        f"{level} Normalized score (the paper's Table 1)",
        "",
        f"Variants run: {', '.join(variants)}. Envs where all of them ran: {', '.join(norm.envs) or 'none'}.",
        "Per env the random policy scores 0 and the best of the variants *run here* scores 1; the paper",
        "took the best of all 11 of its settings, so where fewer are run here the best is easier to be,",
        "and the figures are comparable with the paper's in their order more than in their values.",
        "A score is shown ± its standard error over seeds where every env has 2 or more runs (the paper gives none).",
        "",
        *normalized_table(runs, reference, norm),
        "",
        verdict_text(runs, norm),
        *per_env_lines(runs, norm),
        "",
        f"{level} Scores",
        "",
        *scores.score_table(runs, reference, COLUMNS["table1"], variants, results),
    ]


def summary(folder, runs, reference, results):
    """The README's short table: just the normalized score, the paper's Table 1, and the verdict on its order."""
    norm = normalize(runs, results)
    return [*normalized_table(runs, reference, norm), "", verdict_text(runs, norm)]


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves; returns the markdown."""
    rule = f"{SCORE_RULE} {MUJOCO_VERSIONS}"
    return scores.write_report(folder, runs, reference, results, tables, rule, SOURCES)


def readme_lines(folder, results, reference, full):
    """The suite's lines in a README's Results block (scores.readme_lines)."""
    return scores.readme_lines(folder, load_runs(folder), results, reference, full, tables, summary)


COST_START = "<!-- cost: generated by benchmarks/report.py from the runs' wall times; do not edit by hand -->"
COST_END = "<!-- end of cost -->"


def cost_block(results=RESULTS):
    """What the full Table 1 costs, from the wall time of the 1M-step MuJoCo runs made here (each on one core)."""
    runs = [
        r
        for folder in ("mujoco", "table1")
        if (Path(results) / folder).is_dir()
        for r in load_runs(Path(results) / folder)
    ]
    minutes = [float(r.meta["wall_time_s"]) / 60 for r in runs if "wall_time_s" in r.meta]
    spec = SUITES["table1"]
    full = [(env, variant, seed) for variant in spec.variants for env in spec.envs for seed in spec.seeds]  # 7 envs
    ours = [(env, variant, seed) for env, variant, seed in full if env in TABLE1_ENVS]
    lines = [COST_START, ""]
    if minutes:
        per_run = statistics.mean(minutes)
        todo = sum(not (Path(results) / "table1" / f"{e}__{v}__seed{s}.csv").exists() for e, v, s in ours)
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
