"""The rlhf-long report's answers to its claims, in words that follow the numbers: (a) does a weaker RM peak earlier
and lower, (b) do runs with a KL penalty lie on the unpenalized run's curve, (c) does PPO fall below best-of-N at
equal d, (d) does an ensemble of reward models peak later or higher than one, (e) when the policy falls, do all
members overrate what it writes (herding), or does their disagreement rise first. Every rule reads the peak alike;
(e) reads the falls by a rule (rlhf_series.CURRENT or PREVIOUS), so that the report can set the two side by side."""

from __future__ import annotations

import math

from reports.overoptimization_measures import (
    SUITE,
    WINDOW,
    beta_of,
    binned_gap,
    bon_points,
    cell,
    end,
    end_span,
    ensemble_of,
    fell_of,
    one_outcome_rm,
    over,
    peak_of,
    peak_span,
    per_seed,
    residual,
    rm_pairs,
    single_rm_run,
)
from reports.rlhf_series import CURRENT, SMOOTH, tenths, window_means
from reports.stats import mean_std
from results import ENSEMBLE_STATS
from suites import SUITES


def verdict(values, what):
    """'above <what>', 'below <what>' or 'within 2 standard errors of <what>', by the seeds' mean of `values` against
    its standard error, with the numbers."""
    finite = [v for v in values if math.isfinite(v)]
    if len(finite) < 2:
        return f"{finite[0]:+.2f} from {what} (1 seed)" if finite else f"not comparable with {what}"
    mean, std = mean_std(finite)
    se = std / math.sqrt(len(finite))
    word = "above" if mean > 2 * se else "below" if mean < -2 * se else "within 2 standard errors of"
    return f"{word} {what} ({mean:+.2f} ± {se:.2f}, mean ± standard error over {len(finite)} seeds)"


def claims(series, sft_of, fits, sizes, best):
    """The report's answers to (a), (b) and (c), in words that follow the numbers."""
    import numpy as np

    lines = []
    # (a) peak and its d per RM size, from the runs (their smoothed peak) and from the fits
    parts = []
    by_size = {}
    for pairs in sizes:
        keys = [k for k in series if rm_pairs(k[0]) == pairs and beta_of(k[0]) == 0 and one_outcome_rm(k[0])]
        peaks = [peak_of(series[k], sft_of[k]) for k in keys]
        by_size[pairs] = peaks
        rl = [v for (f, p, _), v in sorted(fits.items()) if f == "rl" and p == pairs]
        parts.append(
            f"{pairs:,} pairs: peak gain {cell([p[0] for p in peaks])} at d {cell([p[1] for p in peaks])}"
            f" (fitted d*, per seed: {per_seed({i: (r[2], r[2] > r[4]) for i, r in enumerate(rl, 1)})})"
        )
    if len(sizes) > 1 and all(by_size.values()):
        low, high = by_size[sizes[0]], by_size[sizes[-1]]
        gain_gap = np.mean([p[0] for p in high]) - np.mean([p[0] for p in low])
        d_gap = np.mean([p[1] for p in low]) - np.mean([p[1] for p in high])
        se = math.sqrt(sum(np.var([p[0] for p in side], ddof=1) / len(side) for side in (low, high) if len(side) > 1))
        lower = "lower" if gain_gap > 2 * se else "not clearly lower" if gain_gap > 0 else "not lower"
        earlier = "earlier" if d_gap < 0 else "not earlier"
        lines.append(
            f"- **(a) Does a weaker RM peak earlier and lower?** Per size, β = 0 runs: {'; '.join(parts)}. The"
            f" {sizes[0]:,}-pair RM's runs peak {lower} than the {sizes[-1]:,}-pair RM's (gap {gain_gap:+.2f} ±"
            f" {se:.2f} standard error) and {earlier} (their peaks' mean d {d_gap:+.2f} from the stronger RM's)."
        )
    # (b) the penalized runs against the same seed's beta-0 run: its points in the bins of d both visited, its fit
    penalized = sorted(k for k in series if beta_of(k[0]) > 0)
    unleashed = {k: single_rm_run(series, k[1], rm_pairs(k[0])) for k in penalized}
    pairs_b = [(k, u) for k, u in unleashed.items() if u is not None and ("rl", rm_pairs(u[0]), u[1]) in fits]
    if pairs_b:
        gaps = [binned_gap(series[k], series[u], sft_of[k]) for k, u in pairs_b]
        res = [residual(series[k], sft_of[k], "rl", fits["rl", rm_pairs(u[0]), u[1]]) for k, u in pairs_b]
        d_end = [math.sqrt(max(end(series[k], "kl"), 0)) for k, _ in pairs_b]
        d_peak = [peak_of(series[u], sft_of[u])[1] for _, u in pairs_b]
        lines.append(
            "- **(b) Does a KL penalty move a run along the β = 0 curve, or onto a better one?** The β > 0 runs' gold"
            " gain, in the bins of d that the same seed's β = 0 run also visited, lies "
            + verdict(gaps, "that run's")
            + "; against that run's fitted curve, "
            + verdict(res, "it")
            + f". They end at d {cell(d_end)}, where the β = 0 runs peaked at d {cell(d_peak)}."
        )
    # (c) PPO against best-of-N at equal d, within the d that best-of-N reaches
    rows = []
    for pairs in sizes:
        for beta in sorted({beta_of(k[0]) for k in series if rm_pairs(k[0]) == pairs}):
            keys = [k for k in series if (rm_pairs(k[0]), beta_of(k[0])) == (pairs, beta) and one_outcome_rm(k[0])]
            keys = [k for k in keys if ("bon", pairs, k[1]) in fits]
            if not keys:
                continue
            d_max = {k: bon_points(best[pairs][k[1]][1])[0].max() for k in keys}
            values = [residual(series[k], sft_of[k], "bon", fits["bon", pairs, k[1]], d_max[k]) for k in keys]
            rows.append(f"{pairs:,} pairs, β = {beta:g}: " + verdict(values, "best-of-N"))
    if rows:
        lines.append(
            "- **(c) Does PPO fall below best-of-N at equal d?** PPO's gold gain minus the same seed's fitted"
            " best-of-N curve at the same d, over its bins of d up to the largest that best-of-N reaches (N = 64): "
            + "; ".join(rows)
            + ". Best-of-N's d is drawn at its KL's upper bound, so at equal true KL its curve lies at least this high"
            " where it rises."
        )
    return lines


def ensemble_claims(series, sft_of, ensemble, rule=CURRENT):
    """The report's answers to (d) and (e), from the ensemble runs and the same seeds' single-RM runs at β = 0; (e)
    reads the falls by `rule`."""
    lines = []
    keys = sorted(k for k in series if ensemble_of(k[0]) > 1)
    parts = []
    for variant in sorted({k[0] for k in keys}, key=list(SUITES[SUITE].variants).index):
        pairs = [(k, single_rm_run(series, k[1], rm_pairs(k[0]))) for k in keys if k[0] == variant]
        pairs = [(k, u) for k, u in pairs if u is not None]
        if not pairs:
            continue
        mine = [peak_of(series[k], sft_of[k]) for k, _ in pairs]
        theirs = [peak_of(series[u], sft_of[u]) for _, u in pairs]
        higher = [m[0] - t[0] for m, t in zip(mine, theirs, strict=True)]
        later = [m[1] - t[1] for m, t in zip(mine, theirs, strict=True)]
        parts.append(
            f"`{variant}` peaks at gold gain {cell([m[0] for m in mine])} at d {cell([m[1] for m in mine])}; minus the"
            f" same seed's single RM, its peak gain is {verdict(higher, 'it')}, and its peak's d"
            f" {verdict(later, 'its')}"
        )
    if parts:
        lines.append(
            "- **(d) Does an ensemble of reward models peak later or higher than one RM on the same pairs?** (Coste et"
            f" al. 2023; peaks on moving averages of {SMOOTH} windows of {WINDOW} iterations, against the same seed's"
            " β = 0 run with one RM) " + "; ".join(parts) + "." + head_lines(series, sft_of, ensemble, keys)
        )
    rows = []
    herded = 0
    first = 0
    fell = fell_of(series, rule)
    for key in [k for k in keys if k in fell and k in ensemble]:
        gold = tenths(series[key], "gold_score", width=WINDOW)
        peak, tail = peak_span(series[key]), end_span(len(gold))
        members = ensemble[key][:, 1 + len(ENSEMBLE_STATS) :]
        windows = [window_means(member, WINDOW) for member in members.T]
        held = sum(over(w, tail) >= over(w, peak) for w in windows)
        spread = window_means(ensemble[key][:, 1 + ENSEMBLE_STATS.index("rm_disagreement")], WINDOW)
        spread = [spread[0], over(spread, peak), over(spread, tail)]
        rose_first = spread[1] > 2 * spread[0]
        herded += held == len(windows)
        first += rose_first
        rows.append(
            f"{key[0]} seed {key[1]}: gold {over(gold, peak):.1f} to {over(gold, tail):.1f}; {held} of"
            f" {len(windows)} members rated the end at least as high as the peak; their disagreement (std over"
            f" members) {spread[0]:.2f} in the first window, {spread[1]:.2f} at the gold peak, {spread[2]:.2f} at the"
            " end"
        )
    if keys:
        fallen, by = len(rows), "the current rule" if rule == CURRENT else "the previous rule"
        answer = (
            f"Of {len(keys)} ensemble runs, {fallen} fell ({by})"
            + (
                f"; in {herded} of them every member rated the fallen text at least as high as the peak's (herding),"
                f" and in {first} the disagreement at the gold peak was more than twice that of the first window: "
                + "; ".join(rows)
                if rows
                else ""
            )
            + "."
        )
        lines.append(
            "- **(e) When the policy falls, do all members overrate what it writes (herding), or does the ensemble's"
            " disagreement rise first?** (Eisenstein et al. 2023: members that share their pretraining, here π_SFT,"
            " share their blind spots) " + answer
        )
    return lines


SAME_HEAD = "-same-head"  # the variants whose members start from one zero head and differ in data order only


def head_lines(series, sft_of, ensemble, keys):
    """(d) for the two kinds of member: how far apart the members are before PPO (their disagreement, the std of their
    scores, on the first rollout's responses, which are pi_SFT's), and seeded heads' peak against the same head's,
    seed by seed, for each aggregate that ran both ways."""
    first = {}
    for key in keys:
        if key in ensemble:
            first.setdefault(key[0], []).append(ensemble[key][0, 1 + ENSEMBLE_STATS.index("rm_disagreement")])
    text = ""
    if first:
        spread = ", ".join(f"`{variant}` {cell(values)}" for variant, values in first.items())
        text += (
            " Before PPO, on the first rollout's 64 responses (π_SFT's), the members disagree (the std of their scores,"
            f" in the RM's normalized units, mean over responses; mean ± std over seeds) by {spread}."
        )
    for variant in sorted({k[0] for k in keys if k[0].endswith(SAME_HEAD)}):
        seeded = variant.removesuffix(SAME_HEAD)
        seeds = sorted(k[1] for k in keys if k[0] == variant and (seeded, k[1]) in series)
        if not seeds:
            continue
        mine = [peak_of(series[seeded, s], sft_of[seeded, s]) for s in seeds]
        theirs = [peak_of(series[variant, s], sft_of[variant, s]) for s in seeds]
        higher = [m[0] - t[0] for m, t in zip(mine, theirs, strict=True)]
        later = [m[1] - t[1] for m, t in zip(mine, theirs, strict=True)]
        text += (
            f" Members with heads of their own (`{seeded}`) against the same seed's members with one head"
            f" (`{variant}`): the peak gain is {verdict(higher, 'theirs')}, and its d {verdict(later, 'theirs')}."
        )
    return text
