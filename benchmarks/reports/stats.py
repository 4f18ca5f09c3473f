"""The statistics over seeds that the reports share: a mean with its sample std, a difference of means with its
standard error, and a run's mean return over all of training."""

from __future__ import annotations

import math
import statistics


def mean_std(values):
    """The mean, and the sample std (None for a single value, which has none)."""
    return statistics.mean(values), (statistics.stdev(values) if len(values) > 1 else None)


def group(runs):
    """{env_id: {variant: [run, ...]}}"""
    out = {}
    for run in runs:
        out.setdefault(run.env_id, {}).setdefault(run.variant, []).append(run)
    return out


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


def mean_return(rows):
    """The paper's other Atari metric (§6.4): the mean score of every episode of training."""
    return statistics.mean(r for _, r, _ in rows)
