"""The rlhf-long report's account of the rule change: every run's verdict of over-optimization and every claim read by
the previous rule (the best single window as the peak; a rise and a fall against the spread within two windows; the
KL and the RM score compared to the last digit) and by the current one (reports/rlhf_series.py), side by side, with
the figures that decided each verdict that changed."""

from __future__ import annotations

import re

from reports.overoptimization_claims import claims, ensemble_claims
from reports.overoptimization_measures import CURRENT, PREVIOUS, SUITE, WINDOW
from reports.rlhf_series import (
    MIN_FALL,
    SMOOTH,
    Z,
    between_window_noise,
    direct_variants,
    judge,
    previous_judgement,
    tenths,
    verdict_of,
)
from suites import SUITES

# The words and counts in which a claim gives its answer: a claim whose words differ between the rules changed its
# verdict; one whose words agree moved at most its numbers.
VERDICT_WORDS = re.compile(
    r"within 2 standard errors of|above|below|not clearly lower|not lower|lower|not earlier|earlier|\d+ fell"
    r"|in \d+ of them|in \d+ the disagreement"
)
NAMES = {"rose": "rise", "fell": "fall", "kl held": "KL change", "score held": "RM score change"}


def reading(run, rule, direct):
    """(over-optimized, {condition: held}, {condition: (change, tolerance)}) of a run under a rule, over windows of
    WINDOW iterations: a rise and a fall in gold, and the KL's and RM score's change from the peak to the end."""
    if rule == CURRENT:
        read = judge(run, WINDOW)
        fell, conditions = verdict_of(read, direct)
        values, tolerance = read["values"], read["tolerance"]
    else:
        fell, conditions, values, tolerance, _ = previous_judgement(run, direct, WINDOW)
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


def change_lines(series, sft_of, fits, sizes, best, ensemble):
    """The report's section on the rule change: the noise the rules see, the per-run verdicts side by side with the
    figures that decided them, the counts per setting, and the claims that changed their verdict."""
    import numpy as np

    direct = direct_variants()
    order = list(SUITES[SUITE].variants)
    variants = sorted({k[0] for k in series}, key=lambda v: (order.index(v) if v in order else len(order), v))
    ratio = []
    for run in series.values():
        means, errors = tenths(run, "gold_score", spread=True, width=WINDOW)
        inside = float(np.median([e for e in errors if e > 0])) if any(e > 0 for e in errors) else 0.0
        if inside > 0:
            ratio.append(between_window_noise(means) / inside)
    lines = [
        "## What the change of rule moved",
        "",
        "The previous rule read the peak as the single window of highest gold, the best of 80 noisy window means, and"
        " judged the rise and the fall against twice the standard error of the difference from the iterations' spread"
        " within the two windows; the KL had to end above its value at the peak and the RM score at least as high, to"
        " the last digit. On these runs the gold's noise between windows is "
        + (f"{min(ratio):.1f} to {max(ratio):.1f} times (median {np.median(ratio):.1f})" if ratio else "not measured")
        + " the standard error the spread within a window gives, so the previous rule judged falls against too small a"
        f" noise. The current rule is stated above: a peak on moving averages of {SMOOTH} windows, a rise and a fall"
        f" past {Z:g} standard errors of the noise between windows and at least {MIN_FALL:g} gold point, the KL and"
        f" the RM score not fallen past {Z:g} standard errors of theirs.",
        "",
        "| setting | seed | previous rule | current rule | what failed, previous rule | what failed, current rule |",
        "|---" * 6 + "|",
    ]
    verdicts = {}
    for key in sorted(series, key=lambda k: (variants.index(k[0]), k[1])):
        old, new = (reading(series[key], rule, key[0] in direct) for rule in (PREVIOUS, CURRENT))
        verdicts[key] = old[0], new[0]
        mark = " (changed)" if old[0] != new[0] else ""
        lines.append(
            f"| {key[0]} | {key[1]} | {'fell' if old[0] else 'no'} | {'fell' if new[0] else 'no'}{mark} |"
            f" {failed(*old[1:])} | {failed(*new[1:])} |"
        )
    # how much the minimum decides: the verdicts that a minimum of 1 gold point, not MIN_FALL, would change
    strict = [k for k in verdicts if verdict_of(judge(series[k], WINDOW, 1.0), k[0] in direct)[0] != verdicts[k][1]]
    counts = []
    for variant in variants:
        keys = [k for k in verdicts if k[0] == variant]
        before, after = (sum(verdicts[k][i] for k in keys) for i in (0, 1))
        counts.append(f"{variant} {before} → {after} of {len(keys)}")
    lines += [
        "",
        "A rise is the gold's change from the first window to the peak; a fall, and the KL's and the RM score's"
        " changes, are from the peak to the end (each rule's peak and end); 'needed' gives what the rule asked of each:"
        " a rise or fall past its tolerance, a change in KL or score not below minus its tolerance (0 under the"
        " previous rule).",
        "",
        "Over-optimized runs per setting, previous rule → current rule: " + ", ".join(counts) + ". With a minimum"
        f" fall of 1 gold point instead of {MIN_FALL:g}, "
        + (", ".join(f"{v} seed {seed}" for v, seed in strict) + " would change" if strict else "no verdict changes")
        + ".",
        "",
    ]
    old = claims(series, sft_of, fits, sizes, best, PREVIOUS) + ensemble_claims(series, sft_of, ensemble, PREVIOUS)
    new = claims(series, sft_of, fits, sizes, best) + ensemble_claims(series, sft_of, ensemble)
    new_of = {line[:8]: line for line in new}
    moved = []
    for line in old:
        letter, now = line[4:7], new_of.get(line[:8], "")
        if VERDICT_WORDS.findall(line) != VERDICT_WORDS.findall(now):
            moved.append(f"{letter} changed its verdict")
        elif line != now:
            moved.append(f"{letter} moved its numbers, not its verdict")
        else:
            moved.append(f"{letter} is unchanged")
    lines += [
        "The claims under the current rule are those above; under the previous rule they read as below. "
        + "; ".join(moved)
        + ".",
        "",
        *old,
    ]
    return lines
