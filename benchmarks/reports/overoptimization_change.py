"""The rlhf-long report's account of the rule change: every run's verdict of over-optimization and every claim that
reads falls, by the previous rule (the noise between windows the rms of every residual, a collapse's included) and by
the current one (reports/rlhf_series.py: the residuals past CLIP robust standard deviations left out), side by side,
with the figures that decided each verdict."""

from __future__ import annotations

import re

from reports.overoptimization_claims import ensemble_claims
from reports.overoptimization_measures import SUITE, WINDOW
from reports.overoptimization_process import overoptimization_lines
from reports.rlhf_series import (
    CLIP,
    CURRENT,
    MIN_FALL,
    PREVIOUS,
    RULES,
    between_window_noise,
    direct_variants,
    judge,
    refreshed,
    tenths,
    verdict_of,
)
from suites import SUITES

# The words and counts in which a claim gives its answer: a claim whose words differ between the rules changed its
# verdict; one whose words agree moved at most its numbers.
VERDICT_WORDS = re.compile(
    r"within 2 standard errors of|above|below|not clearly lower|not lower|lower|not earlier|earlier|\d+ fell"
    r"|in \d+ of them|in \d+ the disagreement|did not fall|(?:rose|fell|held) (?:yes|no)"
)
NAMES = {"rose": "rise", "fell": "fall", "kl held": "KL change", "score held": "RM score change"}


def reading(run, rule, unscored):
    """(over-optimized, {condition: held}, {condition: (change, tolerance)}) of a run under a rule, over windows of
    WINDOW iterations: a rise and a fall in gold, and the KL's and RM score's change from the peak to the end."""
    read = judge(run, WINDOW, rule=rule)
    fell, conditions = verdict_of(read, unscored)
    values, tolerance = read["values"], read["tolerance"]
    (first, peak, last), kl, score = values["gold_score"], values["kl"], values["score"]
    figures = {
        "rose": (peak - first, tolerance["gold_score"][0]),
        "fell": (peak - last, tolerance["gold_score"][1]),
        "kl held": (kl[2] - kl[1], -tolerance["kl"][1]),
        "score held": (score[2] - score[1], -tolerance["score"][1]),
    }
    return fell, conditions, figures


def failed(conditions, figures):
    """The conditions a run failed, with their figures: 'fall +0.55 (needed > +1.67)'; 'all held' if none."""
    out = []
    for name, held in conditions.items():
        if not held:
            change, tolerance = figures[name]
            needed = ">=" if name == "score held" else ">"
            digits = 3 if name == "score held" else 2
            out.append(f"{NAMES[name]} {change:+.{digits}f} (needed {needed} {tolerance:+.{digits}f})")
    return ", ".join(out) or "all held"


def change_lines(folder, series, sft_of, ensemble, results):
    """The report's section on the rule change: the noise each rule sees, the per-run verdicts side by side with the
    figures that decided them, the counts per setting, and the claims that read falls, under the previous rule."""
    import numpy as np

    direct = direct_variants()
    order = list(SUITES[SUITE].variants)
    variants = sorted({k[0] for k in series}, key=lambda v: (order.index(v) if v in order else len(order), v))
    ratio = []
    for run in series.values():
        means = tenths(run, "gold_score", width=WINDOW)
        clipped = between_window_noise(means)
        if clipped > 0:
            ratio.append(between_window_noise(means, RULES[PREVIOUS][1]) / clipped)
    (z, _), (previous_z, _) = RULES[CURRENT], RULES[PREVIOUS]
    lines = [
        "## What the change of rule moved",
        "",
        "The previous rule measured the noise between windows as the rms of every residual (each window against the"
        f" mean of its two neighbours) and asked {previous_z:g} standard errors of it. A collapse, a step down of S,"
        " leaves two residuals of S / 2, which counted as noise and hid the collapse they came from. The current rule"
        f" leaves out the residuals further from their median than {CLIP:g} robust standard deviations (1.4826 times"
        f" their median absolute deviation) and asks {z:g} standard errors of the rms of the rest. On these runs the"
        " gold's noise under the previous rule is "
        + (f"{min(ratio):.1f} to {max(ratio):.1f} times (median {np.median(ratio):.1f})" if ratio else "not measured")
        + " the current rule's.",
        "",
        "| setting | seed | previous rule | current rule | what failed, previous rule | what failed, current rule |",
        "|---" * 6 + "|",
    ]
    verdicts = {}
    for key in sorted(series, key=lambda k: (variants.index(k[0]), k[1])):
        unscored = key[0] in direct or refreshed(key[0])
        old, new = (reading(series[key], rule, unscored) for rule in (PREVIOUS, CURRENT))
        verdicts[key] = old[0], new[0]
        mark = " (changed)" if old[0] != new[0] else ""
        lines.append(
            f"| {key[0]} | {key[1]} | {'fell' if old[0] else 'no'} | {'fell' if new[0] else 'no'}{mark} |"
            f" {failed(*old[1:])} | {failed(*new[1:])} |"
        )
    # how much the minimum decides: the verdicts that a minimum of 1 gold point, not MIN_FALL, would change
    unscored = {k: k[0] in direct or refreshed(k[0]) for k in verdicts}
    strict = [k for k in verdicts if verdict_of(judge(series[k], WINDOW, 1.0), unscored[k])[0] != verdicts[k][1]]
    counts = []
    for variant in variants:
        keys = [k for k in verdicts if k[0] == variant]
        before, after = (sum(verdicts[k][i] for k in keys) for i in (0, 1))
        counts.append(f"{variant} {before} → {after} of {len(keys)}")
    lines += [
        "",
        "A rise is the gold's change from the first window to the peak; a fall, and the KL's and the RM score's"
        " changes, are from the peak to the end; 'needed' gives what the rule asked of each: a rise or fall past its"
        " tolerance, a change in KL or score not below minus its tolerance.",
        "",
        "Over-optimized runs per setting, previous rule → current rule: " + ", ".join(counts) + ". With a minimum"
        f" fall of 1 gold point instead of {MIN_FALL:g}, "
        + (", ".join(f"{v} seed {seed}" for v, seed in strict) + " would change" if strict else "no verdict changes")
        + ".",
        "",
    ]
    # every rule reads the peak alike: the claims that read falls, (e) and (g), are those the change can move
    old = ensemble_claims(series, sft_of, ensemble, PREVIOUS) + overoptimization_lines(folder, series, sft_of, PREVIOUS)
    new = ensemble_claims(series, sft_of, ensemble) + overoptimization_lines(folder, series, sft_of)
    old = [line for line in old if line[4:7] in ("(e)", "(g)")]
    new_of = {line[:8]: line for line in new}
    moved = []
    for line in old:
        letter, now = line[4:7], new_of.get(line[:8], "")
        if VERDICT_WORDS.findall(line) != VERDICT_WORDS.findall(now):
            moved.append(f"{letter} changed its verdict")
        elif line.replace("the previous rule", "the current rule") != now:  # the rule's name aside
            moved.append(f"{letter} moved its numbers, not its verdict")
        else:
            moved.append(f"{letter} is unchanged")
    if not old:
        return lines
    lines += [
        "The claims that read falls, under the current rule, are those above; under the previous rule they read as"
        " below. " + "; ".join(moved) + ".",
        "",
        *old,
    ]
    return lines
