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
    with warnings.catch_warnings():  # an iteration with no pair of different gold has no RM accuracy: nan
        warnings.simplefilter("ignore", RuntimeWarning)
        means = [np.nanmean(column[i : i + width]) for i in range(first, len(column), width)]
        errors = [np.nanstd(column[i : i + width], ddof=1) / np.sqrt(width) for i in range(first, len(column), width)]
    return (means, errors) if spread else means


def direct_variants():
    """The rlhf suite's variants that learn from the preference pairs directly (DPO, KTO): the RM plays no part in
    them."""
    return {variant for variant, (_, flags) in SUITES["rlhf"].variants.items() if {"--dpo", "--kto"} & set(flags)}


def falls(series, direct=(), width=None):
    """{(variant, seed): text} for each run over-optimized (Gao et al. 2022). Its gold score, per tenth of training (or
    per `width` iterations), rose from the first to its peak and fell from the peak to the last, each by more than
    twice the standard error of the difference (the run's own noise); its KL to pi_SFT ended above its value at the
    peak; and its RM score ended at least as high as there, but for a variant in `direct` (DPO, KTO), which never
    sees the RM: Rafailov et al. (2024) find that direct methods over-optimize too. The text names the hack by the
    last window's shares of spam and garbled text."""
    out = {}
    for key, run in sorted(series.items()):
        (gold, error) = tenths(run, "gold_score", spread=True, width=width)
        score, kl = tenths(run, "score", width=width), tenths(run, "kl", width=width)
        peak = max(range(len(gold)), key=gold.__getitem__)

        noise = [2 * (error[peak] ** 2 + e**2) ** 0.5 for e in error]  # of a difference from the peak
        rose, fell = gold[peak] - gold[0] > noise[0], gold[peak] - gold[-1] > noise[-1]
        proxy_held = key[0] in direct or score[-1] >= score[peak]
        if rose and fell and kl[-1] > kl[peak] and proxy_held:
            spam, garbled = tenths(run, "spam", width=width)[-1], tenths(run, "garbled", width=width)[-1]
            hack = f"spam {spam:.2f}" if spam >= garbled else f"garbled {garbled:.2f}"
            if max(spam, garbled) < 0.1:
                overrates = "its implicit reward" if key[0] in direct else "the RM"
                hack = f"well-formed text {overrates} overrates (spam {spam:.2f}, garbled {garbled:.2f})"
            out[key] = f"gold {gold[peak]:.1f} to {gold[-1]:.1f} as KL grew {kl[peak]:.1f} to {kl[-1]:.1f}; {hack}"
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
