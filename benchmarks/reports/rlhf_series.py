"""What the RLHF reports share (reports/rlhf.py for the rlhf suite, reports/overoptimization.py for rlhf-long): a
run's per-iteration series read in windows, which runs measured the RM's accuracy as it is measured now, the verdict
of over-optimization, Gao et al.'s functional forms, and the per-seed figure. Both report modules import this one, and
this one neither of them."""

from __future__ import annotations

import warnings

from reports.base import fmt, save_figure
from reports.stats import mean_std
from results import RLHF_STATS, RM_ACCURACY
from suites import SUITES


def without_old_accuracy(series, runs):
    """The series, with the RM's accuracy and its pairs blanked (nan) for runs whose CSV does not say they measured
    it on RM_ACCURACY's pairs: those made before ppo_rlhf.py counted pairs to one prompt measured something else under
    the same name (a pool of every rollout's first 16 responses, mostly pairs to different prompts)."""
    import numpy as np

    out = dict(series)
    for run in runs:
        if (run.variant, run.seed) in out and run.meta.get("rm_accuracy") != RM_ACCURACY:
            out[run.variant, run.seed] = array = out[run.variant, run.seed].copy()
            array[:, [1 + RLHF_STATS.index("rm_accuracy"), 1 + RLHF_STATS.index("rm_pairs")]] = np.nan
    return out


def cell(values, n=True):
    """'mean ± std (n)' over seeds, or '–' where every value is nan (not measured)."""
    values = [v for v in values if v == v]
    return (fmt(*mean_std(values)) + (f" ({len(values)})" if n else "")) if values else "–"


def fit_gao(d, gain, form):
    """Gao et al. 2022's functional forms of the gold gain over the initial policy against d = sqrt(KL(pi || pi_init)),
    fitted by least squares (both are linear in alpha and beta): best-of-N, R(d) = d (alpha - beta d), and RL,
    R(d) = d (alpha - beta log d). Returns alpha, beta, the peak d* (where dR/dd = 0) and the gain there, R(d*):
    for "bon", d* = alpha / (2 beta) and R* = alpha^2 / (4 beta); for "rl", d* = exp(alpha / beta - 1) and R* = beta d*.
    With beta <= 0 the curve has no peak: d* and R* are inf."""
    import numpy as np

    d = np.asarray(d, dtype=float)
    shape = {"bon": d * d, "rl": d * np.log(np.where(d > 0, d, 1.0))}[form]
    (alpha, beta), *_ = np.linalg.lstsq(np.stack([d, -shape], 1), np.asarray(gain, dtype=float), rcond=None)
    if beta <= 0:
        return float(alpha), float(beta), float("inf"), float("inf")
    with np.errstate(over="ignore"):  # a peak past any float is no peak: inf
        peak = alpha / (2 * beta) if form == "bon" else float(np.exp(alpha / beta - 1.0))
    return float(alpha), float(beta), float(peak), float(alpha**2 / (4 * beta) if form == "bon" else beta * peak)


def tenths(run, name, spread=False, width=None):
    """The mean of a run's rlhf/<name> over each tenth of its iterations (or each `width` of them), in order, counted
    from the end: the last is the mean of the last tenth, as in report.md. With `spread`, also each mean's standard
    error, from the spread of its iterations."""
    column = run[:, 1 + RLHF_STATS.index(name)]
    return window_means(column, width or max(1, len(column) // 10), spread)


def window_means(column, width, spread=False):
    """The mean of a per-iteration column over each window of `width` iterations, counted from the end (tenths()
    reads a run's column so), with each mean's standard error if `spread`."""
    import numpy as np

    first = len(column) % width
    windows = np.asarray(column[first:], dtype=float).reshape(-1, width)  # one row a window
    with warnings.catch_warnings():  # an iteration with no pair of different gold has no RM accuracy: nan
        warnings.simplefilter("ignore", RuntimeWarning)
        means = np.nanmean(windows, axis=1).tolist()
        if not spread:
            return means
        errors = (np.nanstd(windows, axis=1, ddof=1) / np.sqrt(width)).tolist()
    return means, errors


def direct_variants():
    """The rlhf suite's variants that learn from the preference pairs directly (DPO, KTO): the RM plays no part in
    them."""
    return {variant for variant, (_, flags) in SUITES["rlhf"].variants.items() if {"--dpo", "--kto"} & set(flags)}


def refreshed(variant):
    """Whether a variant's reward model keeps learning on the policy's text (--rm-refresh, in either RLHF suite): its
    score at the end is then a later model's than the one that scored the peak, and the two are not compared."""
    suites = (SUITES["rlhf"], SUITES["rlhf-long"])
    return any("--rm-refresh" in suite.variants[variant][1] for suite in suites if variant in suite.variants)


# Over-optimization is judged so that no single noisy window decides it. A run's gold, KL and RM score are read as
# window means; the peak is found on their moving average over SMOOTH windows; every change is judged against the
# noise between windows (below), times Z, and a change in gold must also pass MIN_FALL gold points.
SMOOTH = 3  # windows a moving average spans: the highest of 80 single windows of pure noise sits about 2.5 of their
# standard errors above the curve's level, and a mean of 3 has a third of the variance; 3 windows of 20 iterations
# (3,840 responses of an rlhf-long run's 102,400) still resolve a peak that lasts that long
CLIP = 4.0  # the noise leaves out residuals beyond CLIP robust standard deviations (between_window_noise)
Z = 4.0  # standard errors of a difference that a change must pass. Fixed on flat curves of pure noise, before the runs
# were judged: on 80 or on 10 windows of Gaussian noise the fall alone passes in under 2% of curves, and of noise with
# t's heavy tails (4 degrees of freedom, the runs' plateaus have such tails) in under 5% (tests/test_reports.py)
# MIN_FALL: gold points a rise and a fall must pass, however quiet the run: five times the noise between the windows
# of a plateau (about 0.1). Not 1: the one beta-0 run that falls on well-formed text falls 1.02 points, and a minimum
# at its size would settle its verdict by hundredths, the fragility this rule is here to remove; the rlhf-long report
# says which verdicts a minimum of 1 would change
MIN_FALL = 0.5
# The rules a verdict can be read by: (Z, CLIP) of the current one, and of the previous one, whose noise was the rms of
# every residual (no clip), kept so that the reports can say which verdicts the change moved
CURRENT, PREVIOUS = "current", "previous"
RULES = {CURRENT: (Z, CLIP), PREVIOUS: (3.5, float("inf"))}


def between_window_noise(means, clip=CLIP):
    """The standard deviation of a window mean around its curve, measured between windows: each window against the
    mean of its two neighbours, which takes out a straight trend; for independent noise of std s that residual has
    variance 1.5 s^2. Not the spread within windows, which misses whatever moves a whole window: a plateau's windows
    scatter several times more than their own standard errors say. The residuals further from their median than
    `clip` robust standard deviations (1.4826 times their median absolute deviation, a Gaussian's std) are left out:
    a collapse, a step down of S, leaves two residuals of S / 2, which would otherwise count as noise and hide it; and
    a median alone is no cure, since the plateaus have heavy tails. nan with fewer than 3 windows."""
    import numpy as np

    m = np.asarray(means, dtype=float)
    if len(m) < 3:
        return float("nan")
    residual = m[1:-1] - (m[:-2] + m[2:]) / 2
    distance = np.abs(residual - np.median(residual))
    kept = residual if clip == float("inf") else residual[distance <= clip * 1.4826 * np.median(distance)]
    return float(np.sqrt(np.mean(kept**2) / 1.5))


def smoothed(means, width=SMOOTH):
    """The moving average of window means over `width` windows, one per full span (the first spans windows 0 to
    width - 1); the whole curve's mean where there are fewer windows."""
    import numpy as np

    m = np.asarray(means, dtype=float)
    return np.convolve(m, np.ones(width) / width, mode="valid") if len(m) >= width else np.array([m.mean()])


def judge(run, width=None, min_fall=MIN_FALL, rule=CURRENT):
    """A rule's reading of one run (RULES: the current one unless `rule` says), on window means of `width` iterations
    (a tenth of the run without it): {name: (first window, smoothed peak, smoothed end)} for gold, KL and RM score at
    the smoothed gold peak; the peak's span of windows; and each quantity's tolerance, Z between-window standard errors
    of the difference it is judged by (gold's at least min_fall). The start is the first window alone: the policy
    moves fastest there, and a moving average would mix the start into the rise."""
    import numpy as np

    z, clip = RULES[rule]
    out = {"tolerance": {}, "values": {}}
    for name in ("gold_score", "kl", "score"):
        means = tenths(run, name, width=width)
        curve = smoothed(means)
        if name == "gold_score":
            peak = int(np.argmax(curve))
            out["span"] = (peak, peak + min(SMOOTH, len(means)), len(means))  # first, last (exclusive), of how many
        noise = between_window_noise(means, clip)
        k = min(SMOOTH, len(means))
        out["values"][name] = (float(means[0]), float(curve[peak]), float(curve[-1]))
        fall, rise = z * noise * (2 / k) ** 0.5, z * noise * (1 + 1 / k) ** 0.5
        if name == "gold_score":
            fall, rise = max(min_fall, fall), max(min_fall, rise)
        out["tolerance"][name] = (rise, fall)
    return out


def verdict_of(reading, unscored=False):
    """Whether a reading (judge()) is over-optimization, and the conditions: gold rose from the first window to the
    peak and fell from the peak to the end, each by more than its tolerance; the KL did not end lower than at the peak
    by more than its tolerance; nor the RM score, unless it is not asked (`unscored`): of a method that never sees the
    RM, or of a reward model refreshed on the policy's text, whose score at the end is another model's than at the
    peak. A refreshed model that learns to score fallen text low does not undo the fall its earlier self led to."""
    values, tolerance = reading["values"], reading["tolerance"]
    first, peak, last = values["gold_score"]
    conditions = {
        "rose": peak - first > tolerance["gold_score"][0],
        "fell": peak - last > tolerance["gold_score"][1],
        "kl held": values["kl"][2] > values["kl"][1] - tolerance["kl"][1],
        "score held": unscored or values["score"][2] >= values["score"][1] - tolerance["score"][1],
    }
    return all(conditions.values()), conditions


def hack(run, direct, width=None):
    """The hack by the last window's shares of spam and garbled text."""
    spam, garbled = tenths(run, "spam", width=width)[-1], tenths(run, "garbled", width=width)[-1]
    if max(spam, garbled) < 0.1:
        overrates = "its implicit reward" if direct else "the RM"
        return f"well-formed text {overrates} overrates (spam {spam:.2f}, garbled {garbled:.2f})"
    return f"spam {spam:.2f}" if spam >= garbled else f"garbled {garbled:.2f}"


def falls(series, direct=(), width=None, rule=CURRENT):
    """{(variant, seed): text} for each run over-optimized (Gao et al. 2022), by verdict_of() on a rule's reading
    (judge()) of windows of `width` iterations (tenths without it): gold rose to its peak and fell from it, beyond the
    noise between windows and by at least MIN_FALL gold points, while the KL to pi_SFT and the RM score did not fall
    beyond their noise; the RM score is not asked of a variant in `direct` (DPO, KTO), which never sees the RM:
    Rafailov et al. (2024) find that direct methods over-optimize too; nor of one whose RM is refreshed (refreshed()).
    The text names the hack by the last window's shares of spam and garbled text."""
    out = {}
    for key, run in sorted(series.items()):
        reading = judge(run, width, rule=rule)
        if verdict_of(reading, key[0] in direct or refreshed(key[0]))[0]:
            gold, kl = reading["values"]["gold_score"], reading["values"]["kl"]
            out[key] = (
                f"gold {gold[1]:.1f} to {gold[2]:.1f} as KL went {kl[1]:.1f} to {kl[2]:.1f};"
                f" {hack(run, key[0] in direct, width)}"
            )
    return out


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
