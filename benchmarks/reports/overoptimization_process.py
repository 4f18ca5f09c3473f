"""The rlhf-long report's answers on process supervision (ppo_rlhf.py --reward process), beside the outcome reward model
on the same axes: (f) credit assignment, the gold each reaches early in training at equal responses, before any run
has fallen, and (g) over-optimization, the process arm's peak, whether and how it falls, and whether its reward model
rated the fallen text highly; and the labels each reward model cost. Peaks and falls are read by the same rule as
every other arm."""

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
from reports.rlhf_series import CURRENT, judge, tenths, verdict_of, window_means
from reports.stats import mean_std
from results import PROCESS_STATS, RLHF_STATS, load_runs, read_rlhf_series, read_series

# (process arm, outcome arm at the same beta) in each suite
ARMS = {"rlhf": ("process", "beta0.05"), SUITE: ("process-beta0", "beta0")}
# (f) reads the first EARLY iterations (2,560 responses): in both suites, before any of these runs had fallen, where a
# tenth of an rlhf-long run (160 iterations) holds the collapse of two process runs
EARLY = 40


def first_fall(run, width=None):
    """The first iteration of a run's first window of a fall: after its peak, the first window of `width` iterations
    (a tenth of the run without it) whose gold is below the peak by more than the rule's tolerance of a fall; None for
    a run the rule says did not fall."""
    width = width or max(1, len(run) // 10)
    reading = judge(run, width)
    if not verdict_of(reading)[0]:
        return None
    gold = tenths(run, "gold_score", width=width)
    below = reading["values"]["gold_score"][1] - reading["tolerance"]["gold_score"][1]  # the peak less the tolerance
    first = next(i for i in range(reading["span"][1], len(gold)) if gold[i] < below)
    return len(run) % width + first * width  # windows are counted from the end


def early_gold(series, variant):
    """{seed: the mean gold over the first EARLY iterations} of a variant's runs."""
    return {
        seed: float(run[:EARLY, 1 + RLHF_STATS.index("gold_score")].mean())
        for (v, seed), run in series.items()
        if v == variant
    }


def mean_se(values):
    """'mean ± standard error' over seeds."""
    mean, std = mean_std(values)
    return f"{mean:.2f} ± {std / math.sqrt(len(values)):.2f}" if len(values) > 1 else f"{mean:.2f}"


def credit_lines(folder, series, results):
    """(f): gold over the first EARLY iterations, process against outcome, seed by seed (a seed's pi_SFT and pairs are
    the same for both), in the rlhf suite (the default beta) and in this one (beta 0); and the earliest first window of
    a fall among these runs, which the first EARLY iterations must precede."""
    parts, falls = [], []
    for suite, (process, outcome) in ARMS.items():
        runs = series if suite == SUITE else read_rlhf_series(Path(results) / suite)
        width = WINDOW if suite == SUITE else None  # the windows each suite's verdicts read
        mine, theirs = early_gold(runs, process), early_gold(runs, outcome)
        seeds = sorted(set(mine) & set(theirs))
        if not seeds:
            continue
        falls += [first_fall(runs[k], width) for k in runs if k[0] in (process, outcome) and k[1] in seeds]
        parts.append(
            f"in `{suite}`, `{process}` reached gold {mean_se([mine[s] for s in seeds])} and `{outcome}`"
            f" {mean_se([theirs[s] for s in seeds])} ("
            + ", ".join(f"seed {s}: {mine[s]:.2f} against {theirs[s]:.2f}" for s in seeds)
            + "); process minus outcome, seed by seed, is "
            + verdict([mine[s] - theirs[s] for s in seeds], "the outcome RM")
        )
    if not parts:
        return []
    falls = [f for f in falls if f is not None]
    return [
        "- **(f) Does a reward at each clause assign credit faster than one at the end?** (Uesato et al. 2022,"
        f" Lightman et al. 2023; the mean gold over the first {EARLY} iterations, {EARLY * 64:,} responses; mean ±"
        " standard error over seeds) "
        + "; ".join(parts)
        + ". "
        + (
            f"The earliest first window of a fall among these runs begins at iteration {min(falls) + 1}:"
            + (" these iterations come before any fall." if min(falls) >= EARLY else " within these iterations.")
            if falls
            else "None of these runs fell."
        )
    ]


def overoptimization_lines(folder, series, sft_of, rule=CURRENT):
    """(g): the process arm's peak at beta 0 against the outcome arm's, whether each process run fell (by `rule`), onto
    what text, and whether its reward model rated that text at least as high as the peak (its score, and its accuracy
    on the policy's clauses, there and at the end)."""
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
    fell = fell_of(series, rule)
    rows = []
    for key in keys:
        run = series[key]
        gold = tenths(run, "gold_score", width=WINDOW)
        peak, tail = peak_span(run), end_span(len(gold))
        score = tenths(run, "score", width=WINDOW)
        conditions = verdict_of(judge(run, WINDOW, rule=rule))[1]  # the rule's conditions, each met or not
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
        "- **(g) Does the process reward model over-optimize, and onto what?** (β = 0, "
        + ("the current rule) " if rule == CURRENT else "the previous rule) ")
        + text
        + ". "
        + "; ".join(rows)
        + "."
    ]


def label_lines(folder):
    """What each reward model learned from, per seed: the process RM's clause labels against the comparisons the
    outcome RM learned from, on the same responses."""
    # Each stage-2 reward model once: arms that share a seed and a number of pairs (a process arm and its refreshed
    # twin) start from the same one, which would otherwise be counted twice.
    runs = {(r.seed, r.meta["rm_train_pairs"]): r for r in load_runs(folder) if "rm_clause_labels" in r.meta}
    runs = list(runs.values())
    if not runs:
        return []
    labels = [int(r.meta["rm_clause_labels"]) for r in runs]
    pairs = [int(r.meta["rm_train_pairs"]) for r in runs]
    accuracy = [float(r.meta["rm_held_out_clause_accuracy"]) for r in runs]
    return [
        f"- **The labels each cost.** The process RM learned from {cell(labels)} clause labels (mean ± std over"
        f" {len(runs)} reward models), one for each clause of the {2 * min(pairs):,}–{2 * max(pairs):,} responses of"
        f" the {min(pairs):,}–{max(pairs):,} pairs the outcome RM compares, and rated {cell(accuracy)} of the held-out"
        " pairs' clauses good or bad as gold does. The two are compared at equal texts, not at equal labelling"
        " effort: a clause label asks a reader for a number, a comparison for a choice between two whole responses."
    ]


def process_claims(folder, series, sft_of, results):
    """(f), (g) and the labels, as report lines."""
    return credit_lines(folder, series, results) + overoptimization_lines(folder, series, sft_of) + label_lines(folder)
