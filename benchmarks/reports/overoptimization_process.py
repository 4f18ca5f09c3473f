"""The rlhf-long report's answers on process supervision (ppo_rlhf.py --reward process), beside the outcome reward model
on the same axes: (f) credit assignment, the gold each reaches early in training at equal responses, and (g)
over-optimization, the process arm's peak, whether and how it falls, and whether its reward model rated the fallen
text highly; and the labels each reward model cost. Peaks and falls are read by the same rule as every other arm."""

from __future__ import annotations

import math
from pathlib import Path

from reports.overoptimization_claims import verdict
from reports.overoptimization_measures import (
    SUITE,
    WINDOW,
    cell,
    end,
    end_span,
    fell_of,
    over,
    peak_of,
    peak_span,
)
from reports.rlhf_series import judge, tenths, verdict_of, window_means
from reports.stats import mean_std
from results import PROCESS_STATS, load_runs, read_rlhf_series, read_series
from suites import SUITES

# (process arm, outcome arm at the same beta) in each suite
ARMS = {"rlhf": ("process", "beta0.05"), SUITE: ("process-beta0", "beta0")}


def first_tenth(series, variant):
    """{seed: the mean gold over the first tenth of the run's iterations} of a variant's runs."""
    return {seed: tenths(run, "gold_score")[0] for (v, seed), run in series.items() if v == variant}


def mean_se(values):
    """'mean ± standard error' over seeds."""
    mean, std = mean_std(values)
    return f"{mean:.2f} ± {std / math.sqrt(len(values)):.2f}" if len(values) > 1 else f"{mean:.2f}"


def credit_lines(folder, series, results):
    """(f): gold over the first tenth of training, process against outcome, seed by seed (a seed's pi_SFT and pairs
    are the same for both), in the rlhf suite (the default beta) and in this one (beta 0)."""
    parts = []
    for suite, (process, outcome) in ARMS.items():
        runs = series if suite == SUITE else read_rlhf_series(Path(results) / suite)
        mine, theirs = first_tenth(runs, process), first_tenth(runs, outcome)
        seeds = sorted(set(mine) & set(theirs))
        if not seeds:
            continue
        responses = SUITES[suite].total_timesteps // 10
        parts.append(
            f"in `{suite}` (the first {responses:,} responses), `{process}` reached gold"
            f" {mean_se([mine[s] for s in seeds])} and `{outcome}` {mean_se([theirs[s] for s in seeds])}; process minus"
            " outcome, seed by seed, is"
            f" {verdict([mine[s] - theirs[s] for s in seeds], 'the outcome RM')}"
        )
    if not parts:
        return []
    return [
        "- **(f) Does a reward at each clause assign credit faster than one at the end?** (Uesato et al. 2022,"
        " Lightman et al. 2023; mean ± standard error over seeds of the mean gold over the first tenth of training) "
        + "; ".join(parts)
        + "."
    ]


def overoptimization_lines(folder, series, sft_of):
    """(g): the process arm's peak at beta 0 against the outcome arm's, whether each process run fell, onto what
    text, and whether its reward model rated that text at least as high as the peak (its score, and its accuracy on
    the policy's clauses, there and at the end)."""
    process, outcome = ARMS[SUITE]
    keys = sorted(k for k in series if k[0] == process)
    if not keys:
        return []
    accuracy = read_series(folder, "process")
    peaks = [peak_of(series[k], sft_of[k]) for k in keys]
    text = (
        f"`{process}` peaks at gold gain {cell([p[0] for p in peaks])} at d {cell([p[1] for p in peaks])} (mean ± std"
        " over seeds)"
    )
    theirs = {k[1]: peak_of(series[k], sft_of[k]) for k in series if k[0] == outcome}
    shared = [(p, theirs[k[1]]) for p, k in zip(peaks, keys, strict=True) if k[1] in theirs]
    if shared:
        text += (
            f"; minus the same seed's `{outcome}`, its peak gain is {verdict([p[0] - t[0] for p, t in shared], 'it')},"
            f" and its d {verdict([p[1] - t[1] for p, t in shared], 'its')}"
        )
    fell = fell_of(series)
    rows = []
    for key in keys:
        run = series[key]
        gold = tenths(run, "gold_score", width=WINDOW)
        peak, tail = peak_span(run), end_span(len(gold))
        score = tenths(run, "score", width=WINDOW)
        conditions = verdict_of(judge(run, WINDOW))[1]  # the rule's conditions, each met or not
        row = (
            f"seed {key[1]} {'fell' if key in fell else 'did not fall'} ("
            + ", ".join(f"{name} {'yes' if met else 'no'}" for name, met in conditions.items())
            + f"): gold {gold[0]:.1f} in the first window, {over(gold, peak):.1f} at the peak,"
            f" {over(gold, tail):.1f} at the end, with spam {end(run, 'spam'):.2f} and garbled"
            f" {end(run, 'garbled'):.2f} at the end; its RM's score {over(score, peak):.2f} at the peak,"
            f" {over(score, tail):.2f} at the end"
        )
        if key in accuracy:
            clauses = window_means(accuracy[key][:, 1 + PROCESS_STATS.index("rm_clause_accuracy")], WINDOW)
            row += (
                f", and it rated {over(clauses, peak):.0%} of the policy's clauses as gold does at the peak,"
                f" {over(clauses, tail):.0%} at the end"
            )
        rows.append(row)
    return [
        "- **(g) Does the process reward model over-optimize, and onto what?** (β = 0, the rule above) "
        + text
        + ". "
        + "; ".join(rows)
        + "."
    ]


def label_lines(folder):
    """What each reward model learned from, per seed: the process RM's clause labels against the comparisons the
    outcome RM learned from, on the same responses."""
    runs = [r for r in load_runs(folder) if "rm_clause_labels" in r.meta]
    if not runs:
        return []
    labels = [int(r.meta["rm_clause_labels"]) for r in runs]
    pairs = [int(r.meta["rm_train_pairs"]) for r in runs]
    accuracy = [float(r.meta["rm_held_out_clause_accuracy"]) for r in runs]
    return [
        f"- **The labels each cost.** The process RM learned from {cell(labels)} clause labels (mean ± std over"
        f" {len(runs)} seeds), one for each clause of the {2 * min(pairs):,}–{2 * max(pairs):,} responses of the"
        f" {min(pairs):,}–{max(pairs):,} pairs the outcome RM compares, and rated {cell(accuracy)} of the held-out"
        " pairs' clauses good or bad as gold does. The two are compared at equal texts, not at equal labelling"
        " effort: a clause label asks a reader for a number, a comparison for a choice between two whole responses."
    ]


def process_claims(folder, series, sft_of, results):
    """(f), (g) and the labels, as report lines."""
    return credit_lines(folder, series, results) + overoptimization_lines(folder, series, sft_of) + label_lines(folder)
