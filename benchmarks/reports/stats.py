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


def welch(scores, base_scores):
    """Welch's t-test of two samples with unequal variances: (t, the Welch-Satterthwaite degrees of freedom, the
    two-sided p-value), for scores minus base_scores; None unless both sides have 2 or more seeds. The p-value is
    1 - 2 x the integral of Student's t density from 0 to |t| (Simpson's rule on 2,000 intervals).

    >>> round(welch([1.0, 2.0, 3.0], [0.0, 0.5, 1.0])[0], 3)  # (2 - 0.5) / sqrt(1 / 3 + 0.25 / 3)
    2.324
    """
    diff = difference(scores, base_scores)
    if diff is None:
        return None
    t = diff[0] / diff[1]
    va, vb = statistics.variance(scores) / len(scores), statistics.variance(base_scores) / len(base_scores)
    df = (va + vb) ** 2 / (va**2 / (len(scores) - 1) + vb**2 / (len(base_scores) - 1))
    scale = math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)) / math.sqrt(df * math.pi)
    n, h = 2000, abs(t) / 2000
    density = [scale * (1 + (i * h) ** 2 / df) ** (-(df + 1) / 2) for i in range(n + 1)]
    integral = h / 3 * (density[0] + density[-1] + 4 * sum(density[1:-1:2]) + 2 * sum(density[2:-1:2]))
    return t, df, max(0.0, 1.0 - 2.0 * integral)


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
