"""What the rlhf-long report measures, shared by its claims, its figure and its account of the rule change: which
reward model and KL coefficient a variant has, a run's points in bins of d = sqrt(KL[pi || pi_SFT]), Gao et al.'s
forms, and a run's peak, its end, and its verdict of over-optimization under a rule (reports/rlhf_series.py: the
current one, or the previous one, kept so that the report can say which verdicts the change moved)."""

from __future__ import annotations

import math
from pathlib import Path

from reports.base import fmt, ordered_variants
from reports.rlhf_series import CURRENT, SMOOTH, direct_variants, falls, fit_gao, judge, tenths
from reports.stats import mean_std
from results import BEST_OF_N, RLHF_STATS, read_best_of_n, read_rlhf_series
from suites import SUITES

SUITE = "rlhf-long"
DEFAULT_PAIRS = 4096  # ppo_rlhf.py's --rm-pairs: its best-of-N curves are the rlhf suite's
WINDOW = 20  # iterations a point stands for (1,280 responses, a tenth of an rlhf-suite run): a peak early in a long
# run is not averaged away in a tenth of it
D_BIN = 0.2  # the width in d of the bins a run's iterations are averaged over for a fit
FORMS = {"bon": "best-of-N, d (α − β d)", "rl": "RL, d (α − β log d)"}


def rm_pairs(variant, suite=SUITE):
    """The --rm-pairs of a variant's flags, or the script's default (4,096)."""
    flags = SUITES[suite].variants[variant][1]
    return int(flags[flags.index("--rm-pairs") + 1]) if "--rm-pairs" in flags else DEFAULT_PAIRS


def ensemble_of(variant, suite=SUITE):
    """The --rm-ensemble of a variant's flags: its number of reward models (1 without the flag)."""
    flags = SUITES[suite].variants[variant][1]
    return int(flags[flags.index("--rm-ensemble") + 1]) if "--rm-ensemble" in flags else 1


def reward_of(variant, suite=SUITE):
    """A variant's kind of reward model: "process" with --reward process, else "outcome"."""
    flags = SUITES[suite].variants[variant][1]
    return flags[flags.index("--reward") + 1] if "--reward" in flags else "outcome"


def refresh_of(variant, suite=SUITE):
    """The --rm-refresh of a variant's flags: every how many iterations its reward model learns on the policy's text
    (0 without the flag: never)."""
    flags = SUITES[suite].variants[variant][1]
    return int(flags[flags.index("--rm-refresh") + 1]) if "--rm-refresh" in flags else 0


def one_outcome_rm(variant, suite=SUITE):
    """Whether a variant learns from one outcome reward model, fixed after stage 2: no ensemble, no process
    supervision, no refresh."""
    return (
        ensemble_of(variant, suite) == 1 and reward_of(variant, suite) == "outcome" and not refresh_of(variant, suite)
    )


def best_of_n_folder(results, pairs):
    """Where best_of_n.py's CSVs for reward models of `pairs` pairs are: the rlhf suite's own for the default size."""
    return Path(results) / "rlhf" if pairs == DEFAULT_PAIRS else Path(results) / SUITE / f"rm{pairs}"


def end(run, name):
    """The mean of a run's rlhf/<name> over its last WINDOW iterations."""
    return tenths(run, name, width=WINDOW)[-1]


def column(run, name):
    return run[:, 1 + RLHF_STATS.index(name)]


def points(run, gold_sft):
    """A run's (d, gold gain over pi_SFT), its iterations averaged within bins of D_BIN in d, d = sqrt(KL) of each
    iteration's responses: one point a bin, so that a run that stalls at one KL does not weigh that KL more."""
    import numpy as np

    d, gain = np.sqrt(np.clip(column(run, "kl"), 0, None)), column(run, "gold_score") - gold_sft
    bins = np.floor(d / D_BIN)
    return tuple(np.array([x[bins == b].mean() for b in np.unique(bins)]) for x in (d, gain))


def bon_points(table):
    """Best-of-N's (d, gold gain over N = 1) at each N, d from the KL's upper bound log N - (N - 1) / N."""
    import numpy as np

    gold = table[:, BEST_OF_N.index("gold_score")]
    return np.sqrt(table[:, BEST_OF_N.index("kl")]), gold - gold[0]


def curve(form, alpha, beta, d):
    import numpy as np

    d = np.asarray(d, dtype=float)
    return d * (alpha - beta * (d if form == "bon" else np.log(np.where(d > 0, d, 1.0))))


def cell(values):
    """'mean ± std' of the finite values, and how many had no peak (inf), if any; nan (not measured) is left out."""
    finite = [v for v in values if math.isfinite(v)]
    peakless = sum(v == math.inf for v in values)
    text = f"{fmt(*mean_std(finite))}" if finite else "–"
    return text + (f" ({peakless} without a peak)" if peakless else "")


def per_seed(values):
    """'seed: value' for each seed, a † after a value from a peak past the data ({seed: (value, past)})."""
    return "; ".join(f"{seed}: {fmt(v)}{'†' if past else ''}" for seed, (v, past) in sorted(values.items()))


def peak_span(run):
    """The windows of WINDOW iterations the run's gold peak spans (first, last exclusive): the SMOOTH windows of the
    highest moving average (every rule reads the peak so)."""
    return judge(run, WINDOW)["span"][:2]


def end_span(count):
    """The windows a run's end spans, of `count`: the last SMOOTH."""
    return max(0, count - SMOOTH), count


def over(means, span):
    """The mean of window means over a span of windows."""
    return float(sum(means[span[0] : span[1]]) / (span[1] - span[0]))


def peak_of(run, gold_sft):
    """The run's gold gain over pi_SFT at its peak (the mean of the windows it spans) and the d of their mean KL."""
    span = peak_span(run)
    kl = over(tenths(run, "kl", width=WINDOW), span)
    return over(tenths(run, "gold_score", width=WINDOW), span) - gold_sft, math.sqrt(max(kl, 0.0))


def fell_of(series, rule=CURRENT):
    """{(variant, seed): text} for each run over-optimized under the rule, over windows of WINDOW iterations."""
    return falls(series, direct_variants(), WINDOW, rule)


def residual(run, gold_sft, form, params, d_max=math.inf):
    """The mean of a run's gold gain minus the fitted curve at the same d, over its points (bins of d) with d <= d_max
    (nan if none): above 0, the run lies above that curve."""
    import numpy as np

    d, gain = points(run, gold_sft)
    keep = d <= d_max
    return float(np.mean(gain[keep] - curve(form, *params[:2], d[keep]))) if keep.any() else float("nan")


def binned_gap(run, other, gold_sft):
    """The mean over the bins of d that both runs visited of run's gold gain minus other's (nan if none)."""
    import numpy as np

    (d, gain), (d_other, gain_other) = points(run, gold_sft), points(other, gold_sft)
    mine = dict(zip(np.floor(d / D_BIN), gain, strict=True))
    theirs = dict(zip(np.floor(d_other / D_BIN), gain_other, strict=True))
    shared = sorted(set(mine) & set(theirs))
    return float(np.mean([mine[b] - theirs[b] for b in shared])) if shared else float("nan")


def measure(folder, runs, results):
    """What the report and the README's summary read: (series, variants, held-out RM accuracy per run, RM sizes,
    best-of-N tables per size and seed, pi_SFT's gold per run, Gao's fits per (form, size, seed))."""
    series = read_rlhf_series(folder)
    variants = ordered_variants(SUITE, runs)
    held_out = {
        (r.variant, r.seed): float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta
    }
    sizes = sorted({rm_pairs(v) for v in variants})
    seeds = {seed for _, seed in series}  # best-of-N of these seeds' reward models only
    best = {p: {s: t for s, t in read_best_of_n(best_of_n_folder(results, p)).items() if s in seeds} for p in sizes}
    # pi_SFT's gold, from best-of-N's N = 1 (pi_SFT's own samples, the same for every RM of a seed), else the run's
    # first iteration
    gold_sft = {}
    for tables in best.values():
        for seed, (_, table) in tables.items():
            gold_sft.setdefault(seed, table[0, BEST_OF_N.index("gold_score")])
    sft_of = {key: gold_sft.get(key[1], column(run, "gold_score")[0]) for key, run in series.items()}
    # Gao et al.'s forms, fitted per seed: best-of-N to its 7 points, RL to the beta-0 runs' bins of d
    fits = {}  # (form, pairs, seed) -> (alpha, beta, d*, R*, the largest d fitted)
    for pairs in sizes:
        for seed, (_, table) in best[pairs].items():
            d, gain = bon_points(table)
            fits["bon", pairs, seed] = (*fit_gao(d, gain, "bon"), float(d.max()))
        for (variant, seed), run in series.items():
            if rm_pairs(variant) == pairs and beta_of(variant) == 0 and one_outcome_rm(variant):
                d, gain = points(run, sft_of[variant, seed])
                fits["rl", pairs, seed] = (*fit_gao(d, gain, "rl"), float(d.max()))
    return series, variants, held_out, sizes, best, sft_of, fits


def flags_of(variant, suite=SUITE):
    return SUITES[suite].variants[variant][1]


def beta_of(variant, suite=SUITE):
    """The KL coefficient of a variant: its --kl-coef, or the script's default 0.05."""
    flags = flags_of(variant, suite)
    return float(flags[flags.index("--kl-coef") + 1]) if "--kl-coef" in flags else 0.05


def single_rm_run(series, seed, pairs):
    """The key of the seed's β = 0 run with one reward model of `pairs` pairs, or None."""
    keys = [k for k in series if k[1] == seed and beta_of(k[0]) == 0 and rm_pairs(k[0]) == pairs]
    return next((k for k in keys if one_outcome_rm(k[0])), None)
