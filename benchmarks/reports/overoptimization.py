"""The rlhf-long family: over-optimization measured as Gao et al. 2022 (arXiv:2210.10760) measured it. Runs long
enough to pass the gold peak; gold against d = sqrt(KL[pi || pi_SFT]); their functional forms fitted for each reward
model size, to best-of-N (R = d (alpha - beta d)) and to the RL runs (R = d (alpha - beta log d)); and the three
claims the issues ask about, answered from those numbers: (a) does a weaker RM peak earlier and lower, (b) do runs
with a KL penalty lie on the unpenalized run's curve, stopping earlier, (c) does PPO fall below best-of-N at equal d,
(d) does an ensemble of reward models peak later or higher than one, and (e) when the policy falls, do all members
overrate what it writes (herding), or does their disagreement rise first. The figure has a panel each for the KL
penalty, the group baselines, DPO, IPO and KTO (the rlhf suite's arms), the RM size and the ensembles."""

from __future__ import annotations

import math
from pathlib import Path

from reports.base import fmt, ordered_variants, provenance, save_figure
from reports.rlhf_series import direct_variants, falls, fit_gao, plot_rlhf_seeds, tenths, window_means
from reports.stats import mean_std
from results import (
    BEST_OF_N,
    ENSEMBLE_STATS,
    RLHF_STATS,
    load_runs,
    read_best_of_n,
    read_ensemble_series,
    read_rlhf_series,
)
from suites import SUITES

ORDER = 0
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


def peak_of(run, gold_sft):
    """The run's highest mean gold gain over a window of WINDOW iterations, and the d of that window's mean KL."""
    import numpy as np

    gain = [g - gold_sft for g in tenths(run, "gold_score", width=WINDOW)]
    d = np.sqrt(np.clip(tenths(run, "kl", width=WINDOW), 0, None))
    i = int(np.argmax(gain))
    return gain[i], float(d[i])


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
            if rm_pairs(variant) == pairs and beta_of(variant) == 0 and ensemble_of(variant) == 1:
                d, gain = points(run, sft_of[variant, seed])
                fits["rl", pairs, seed] = (*fit_gao(d, gain, "rl"), float(d.max()))
    return series, variants, held_out, sizes, best, sft_of, fits


def summary_lines(folder, results):
    """The README's lines on this suite: its runs, and the claims' answers."""
    runs = load_runs(folder)
    series, _, _, sizes, best, sft_of, fits = measure(folder, runs, results)
    steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in runs}))
    seeds = ", ".join(map(str, sorted({r.seed for r in runs})))
    lines = [
        f"- **Past the gold peak** (`rlhf-long`: {len(runs)} runs of {steps} responses, seeds {seeds}, β = 0 with"
        f" reward models from {', '.join(f'{p:,}' for p in sizes)} pairs and β = 0.05; [report, fits and figure]"
        "(results/rlhf-long/report.md)), as Gao et al. 2022 measured over-optimization:"
    ]
    fell = falls(series, direct_variants(), WINDOW)
    counts = []
    for variant in ordered_variants(SUITE, runs):
        keys = [k for k in series if k[0] == variant]
        garbled = sum(k in fell and end(series[k], "garbled") > 0.5 for k in keys)
        counts.append(f"{variant} {sum(k in fell for k in keys)} of {len(keys)} ({garbled} onto garbled text)")
    lines.append(f"  - **Over-optimized** (the rule above, over windows of {WINDOW} iterations): {', '.join(counts)}.")
    claimed = claims(series, sft_of, fits, sizes, best) + ensemble_claims(series, sft_of, read_ensemble_series(folder))
    return lines + [f"  {line}" for line in claimed]


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves; returns the markdown."""
    import numpy as np

    folder = Path(folder)
    series, variants, held_out, sizes, best, sft_of, fits = measure(folder, runs, results)

    lines = [f"# {folder.name}: over-optimization, as Gao et al. 2022 measured it", "", "Generated by"]
    lines[-1] += " `benchmarks/report.py`."
    lines += ["", *provenance(runs), ""]
    lines += [
        "Each run trains its own stages 1 and 2 (π_SFT depends only on the seed, the reward model on the seed and its"
        " number of pairs) and then PPO for the whole budget. d = sqrt(KL[π || π_SFT]), the KL of each iteration's"
        " responses in nats; a gold gain is the gold score minus π_SFT's (best-of-N's N = 1 of the seed).",
        "",
        *pilot_lines(folder),
        "| setting | RM pairs | RM accuracy, held out | gold at the end | peak gold | d at the peak | d at"
        " the end | RM score at the end | spam | garbled | RM accuracy, recent pairs to one prompt | over-optimized |",
        "|---" * 12 + "|",
    ]
    fell = falls(series, direct_variants(), WINDOW)
    for variant in variants:
        keys = sorted(k for k in series if k[0] == variant)
        peaks = [peak_of(series[k], sft_of[k]) for k in keys]
        members = f" × {ensemble_of(variant)}" if ensemble_of(variant) > 1 else ""
        cells = [f"{rm_pairs(variant):,}{members}", cell([held_out[k] for k in keys if k in held_out])]
        cells.append(cell([end(series[k], "gold_score") for k in keys]))
        cells.append(cell([p[0] + sft_of[k] for p, k in zip(peaks, keys, strict=True)]))
        cells.append(cell([p[1] for p in peaks]))
        cells.append(cell([math.sqrt(max(end(series[k], "kl"), 0)) for k in keys]))
        for name in ("score", "spam", "garbled", "rm_accuracy"):
            cells.append(cell([end(series[k], name) for k in keys]))
        cells.append(f"{sum(k in fell for k in keys)} of {len(keys)}")
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Mean ± std over seeds of each run's means over windows of {WINDOW} iterations ({WINDOW * 64:,} responses):"
        " its last window, and its window of highest gold (the peak). The RM's accuracy on recent pairs counts the"
        " pairs of responses to one prompt, of different gold, among the last 640 the policy wrote (the kind of pair"
        " the RM learned from); – where the policy wrote one response a prompt. A run is over-optimized where its gold"
        " rose from the first window to the peak and fell from the peak to the last window, each by more than twice"
        " the standard error of the difference (from the iterations' spread within the windows), while its KL ended"
        " above its value at the peak and its RM score ended at least as high.",
        "",
        "Per seed:",
        "",
        "| setting | seed | gold: first window, peak, last | KL at the peak, at the end | over-optimized |",
        "|---" * 5 + "|",
    ]
    for key in sorted(series, key=lambda k: (variants.index(k[0]) if k[0] in variants else 99, k[1])):
        gold, kl = tenths(series[key], "gold_score", width=WINDOW), tenths(series[key], "kl", width=WINDOW)
        i = int(np.argmax(gold))
        lines.append(
            f"| {key[0]} | {key[1]} | {gold[0]:.2f}, {gold[i]:.2f} (window {i + 1} of {len(gold)}), {gold[-1]:.2f} |"
            f" {kl[i]:.1f}, {kl[-1]:.1f} | {fell.get(key, 'no')} |"
        )

    lines += [
        "",
        "## Gao et al.'s functional forms, fitted per reward model size",
        "",
        "Least squares of the gold gain on each form (linear in α and β), per seed: best-of-N's 7 points (N = 1 ... 64,"
        f" at the upper bound of its KL) and the β = 0 runs' iterations, averaged in bins of {D_BIN} in d (so that the"
        " KL where a run stalls weighs as much as any other). α and β: mean ± std over seeds. d* is the fitted peak"
        " and the gold there π_SFT's plus the fitted gain R*, seed by seed (seed: value); † marks a peak past the"
        " largest d fitted, an extrapolation (best-of-N's d reaches"
        f" {math.sqrt(math.log(64) - 63 / 64):.2f}, at N = 64); a fit with β ≤ 0 has no peak (inf).",
        "",
        "| RM pairs | RM accuracy, held out | fit | α | β | d*, per seed | gold at d*, per seed |",
        "|---" * 7 + "|",
    ]
    g0 = {seed: value for (_, seed), value in sft_of.items()}
    for pairs in sizes:
        accuracy = [held_out[k] for k in held_out if rm_pairs(k[0]) == pairs and ensemble_of(k[0]) == 1]  # one RM's
        for form in FORMS:
            rows = {seed: v for (f, p, seed), v in sorted(fits.items()) if f == form and p == pairs}
            if rows:
                cells = [cell([r[j] for r in rows.values()]) for j in range(2)]
                cells.append(per_seed({seed: (r[2], r[2] > r[4]) for seed, r in rows.items()}))
                cells.append(per_seed({seed: (g0[seed] + r[3], r[2] > r[4]) for seed, r in rows.items()}))
                lines.append(f"| {pairs:,} | {cell(accuracy)} | {FORMS[form]} | " + " | ".join(cells) + " |")
    lines += ["", "## The claims, from these numbers", ""]
    lines += claims(series, sft_of, fits, sizes, best)
    ensemble = read_ensemble_series(folder)
    lines += ensemble_claims(series, sft_of, ensemble)
    lines += [
        "",
        "![gold against sqrt(KL), per panel](curves/panels.png)",
        "",
        f"Each arm is its gold against d in bins of {D_BIN}: the mean over the seeds that reached a bin of each one's"
        " mean gold there, with a band of ± their std, and each seed's end (the mean of its last window) marked"
        " (o). Every panel has best-of-N from π_SFT (dots: the mean over seeds; dashed: Gao's best-of-N"
        " form fitted to all seeds' points, to 1.5 times its last d) and Gao's RL form fitted to the β = 0 runs"
        " (dotted), for the default RM;"
        " the RM-size panel has them for each size, in its color. The first three panels are the rlhf suite's arms"
        f" ({SUITES['rlhf'].total_timesteps:,} responses a run) beside this suite's.",
        "",
        "Per seed, the gold score (solid, left axis) and the RM's score (dashed, right axis) against sqrt(KL), each a"
        " moving average over 10 iterations, with the gold score's peak marked:",
        "",
        "![per seed](curves/seeds.png)",
    ]
    plot_panels(folder, series, sft_of, fits, best, results)
    plot_rlhf_seeds(folder, series, variants)
    text = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(text)
    return text


def pilot_lines(folder):
    """For the suite's own folder: what the pilot runs at other budgets (folders <suite>_<budget>, seeds outside the
    suite's) showed: those from which the length was chosen, and those of the ensembles, from which the second
    ensemble arm's aggregate was chosen (the higher gold peak, a rule fixed before the pilot ran)."""
    folder = Path(folder)
    lines = {"length": [], "ensemble": []}
    for other in sorted(folder.parent.glob(f"{SUITE}_*")) if folder.name == SUITE else []:
        for (variant, seed), run in sorted(read_rlhf_series(other).items()):
            gold, kl = tenths(run, "gold_score", width=WINDOW), tenths(run, "kl", width=WINDOW)
            i = max(range(len(gold)), key=gold.__getitem__)
            link = f"[{other.name}](../{other.name}/report.md)"
            lines["ensemble" if ensemble_of(variant) > 1 else "length"].append(
                f"- Pilot `{variant}`, seed {seed}, {len(run) * 64:,} responses ({link}):"
                f" gold {gold[0]:.1f} in its first window of {WINDOW * 64:,} responses, {gold[i]:.1f} at its peak in"
                f" window {i + 1} (KL {kl[i]:.1f}), {gold[-1]:.1f} at the end (KL {kl[-1]:.1f})."
            )
    out = []
    if lines["length"]:
        out += [
            f"The length, {SUITES[SUITE].total_timesteps:,} responses, is that of the pilot runs below, on a seed"
            " outside the suite's, chosen from them: where the rlhf suite's β = 0 seeds had not all fallen by"
            f" {SUITES['rlhf'].total_timesteps:,} responses, the pilots peaked within their first tenth and fell long"
            " before their end, so a peak several times later would still show.",
            "",
            *lines["length"],
            "",
        ]
    if lines["ensemble"]:
        out += [
            "The second ensemble arm's aggregate, min or uwo, is the one whose pilot below peaked higher in gold (a"
            " rule fixed before they ran); the other ran only as a pilot.",
            "",
            *lines["ensemble"],
            "",
        ]
    return out


def flags_of(variant, suite=SUITE):
    return SUITES[suite].variants[variant][1]


def beta_of(variant, suite=SUITE):
    """The KL coefficient of a variant: its --kl-coef, or the script's default 0.05."""
    flags = flags_of(variant, suite)
    return float(flags[flags.index("--kl-coef") + 1]) if "--kl-coef" in flags else 0.05


def claims(series, sft_of, fits, sizes, best):
    """The report's answers to (a), (b) and (c), in words that follow the numbers."""
    import numpy as np

    lines = []
    # (a) peak and its d per RM size, from the runs (their best window) and from the fits
    parts = []
    by_size = {}
    for pairs in sizes:
        keys = [k for k in series if rm_pairs(k[0]) == pairs and beta_of(k[0]) == 0 and ensemble_of(k[0]) == 1]
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
            keys = [k for k in series if (rm_pairs(k[0]), beta_of(k[0]), ensemble_of(k[0])) == (pairs, beta, 1)]
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


def single_rm_run(series, seed, pairs):
    """The key of the seed's β = 0 run with one reward model of `pairs` pairs, or None."""
    keys = [k for k in series if k[1] == seed and beta_of(k[0]) == 0 and rm_pairs(k[0]) == pairs]
    return next((k for k in keys if ensemble_of(k[0]) == 1), None)


def ensemble_claims(series, sft_of, ensemble):
    """The report's answers to (d) and (e), from the ensemble runs and the same seeds' single-RM runs at β = 0."""
    import numpy as np

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
            " al. 2023; peaks over windows of 20 iterations, against the same seed's β = 0 run with one RM) "
            + "; ".join(parts)
            + "."
        )
    rows = []
    herded = 0
    first = 0
    fell = falls(series, direct_variants(), WINDOW)
    for key in [k for k in keys if k in fell and k in ensemble]:
        gold = tenths(series[key], "gold_score", width=WINDOW)
        peak = int(np.argmax(gold))
        members = ensemble[key][:, 1 + len(ENSEMBLE_STATS) :]
        windows = [window_means(member, WINDOW) for member in members.T]
        held = sum(w[-1] >= w[peak] for w in windows)
        spread = window_means(ensemble[key][:, 1 + ENSEMBLE_STATS.index("rm_disagreement")], WINDOW)
        rose_first = spread[peak] > 2 * spread[0]
        herded += held == len(windows)
        first += rose_first
        rows.append(
            f"{key[0]} seed {key[1]}: gold {gold[peak]:.1f} to {gold[-1]:.1f}; {held} of {len(windows)} members"
            f" rated the last window at least as high as the peak's; their disagreement (std over members)"
            f" {spread[0]:.2f} in the first window, {spread[peak]:.2f} at the gold peak, {spread[-1]:.2f} at the end"
        )
    if keys:
        fallen = len(rows)
        answer = (
            f"Of {len(keys)} ensemble runs, {fallen} fell (the rule above)"
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


def arm_curve(runs):
    """An arm's gold against d: for each bin of D_BIN in d that a seed visited, the bin's middle, the mean over those
    seeds of each one's mean gold in it, and their std (0 where one seed visited it)."""
    import numpy as np

    per_seed = [dict(zip(np.floor(d / D_BIN), gold, strict=True)) for d, gold in (points(run, 0.0) for run in runs)]
    bins = sorted(set().union(*per_seed))
    values = [[seed[b] for seed in per_seed if b in seed] for b in bins]
    spread = [np.std(v, ddof=1) if len(v) > 1 else 0.0 for v in values]
    return (np.array(bins) + 0.5) * D_BIN, np.array([np.mean(v) for v in values]), np.array(spread)


def plot_panels(folder, series, sft_of, fits, best, results):
    """<folder>/curves/panels.png: gold against d in four panels (the KL penalty, the group baselines, DPO, the RM
    size), with best-of-N and Gao's fitted forms in each, and the legends under the panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    short_folder = Path(results) / "rlhf"
    short = read_rlhf_series(short_folder) if (short_folder / "rlhf").is_dir() else {}
    g0 = float(np.mean(list(sft_of.values()))) if sft_of else 0.0
    short_names = set(SUITES["rlhf"].variants)

    def arms(names, source):
        return [
            (f"{n} ({'long' if source is series else '12.8k'})", n, source)
            for n in names
            if any(k[0] == n for k in source)
        ]

    panels = [
        (
            "KL penalty β",
            arms(["beta0", "beta0.05"], series)
            + arms([n for n in ("beta0.01", "beta0.2", "adaptive") if n in short_names], short),
        ),
        ("group baselines (β = 0.05)", arms(["grpo", "dr-grpo", "rloo", "beta0.05"], short)),
        ("DPO, IPO and KTO (no reward model)", arms(["dpo0.1", "dpo0.5", "ipo0.1", "kto0.1", "kto0.1-tenth"], short)),
        (
            "reward model size (β = 0)",
            arms([v for v in SUITES[SUITE].variants if beta_of(v) == 0 and ensemble_of(v) == 1], series),
        ),
        (
            f"reward-model ensembles (β = 0, {DEFAULT_PAIRS:,} pairs)",
            arms(["beta0", *(v for v in SUITES[SUITE].variants if ensemble_of(v) > 1)], series),
        ),
    ]
    panels = [(title, members) for title, members in panels if members or title.startswith("KL")]
    fig, axes = plt.subplots((len(panels) + 1) // 2, 2, figsize=(11, 5.5 * ((len(panels) + 1) // 2)), sharey=True)
    for ax in axes.flat[len(panels) :]:
        ax.axis("off")
    low, high = g0, g0  # the gold the arms reach, to which the fitted curves are cut
    for ax, (title, members) in zip(axes.flat, panels, strict=False):
        rm_panel = title.startswith("reward model")
        d_max = 1.5 * math.sqrt(math.log(64) - 63 / 64)  # the panel's widest d: best-of-N's dashed curve, or an arm's
        for i, (label, variant, source) in enumerate(members):
            color = f"C{i}"
            keys = sorted(k for k in source if k[0] == variant)
            x, y, spread = arm_curve([source[k] for k in keys])
            d_max, low, high = max(d_max, x.max()), min(low, (y - spread).min()), max(high, (y + spread).max())
            ax.plot(x, y, "-", color=color, lw=1.5, label=f"{label}, {len(keys)} seeds")
            ax.fill_between(x, y - spread, y + spread, color=color, alpha=0.15, lw=0)
            for k in keys:  # each seed's end: seeds that end apart are not averaged into a point none of them reached
                ax.plot(
                    math.sqrt(max(end(source[k], "kl"), 0)),
                    end(source[k], "gold_score"),
                    "o",
                    color=color,
                    ms=5,
                    mfc="white",
                    mew=1.2,
                )
            if rm_panel:
                draw_reference(ax, rm_pairs(variant), fits, best, g0, color, label=False)
        if not rm_panel:
            draw_reference(ax, DEFAULT_PAIRS, fits, best, g0, "k", label=True)
        ax.plot(0, g0, "k*", ms=9, label="π_SFT" if not rm_panel else None)
        ax.set_title(title, fontsize=10)
        ax.set_xlim(0, d_max * 1.05)
        ax.set_xlabel("d = sqrt(KL[π || π_SFT]), nats^0.5", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    axes[0, 0].set_ylim(low - 1, high + 1)
    for ax in axes[:, 0]:
        ax.set_ylabel("gold score")
    fig.suptitle(
        "dots: best-of-N (N = 1 ... 64), d at its KL's upper bound; dashed: its fitted d (α − β d), to 1.5 times its"
        " last d; dotted: the β = 0 runs' fitted d (α − β log d), to their largest d; o: each seed's end; *: π_SFT",
        fontsize=8,
    )
    return save_figure(fig, folder, "panels.png")


def draw_reference(ax, pairs, fits, best, g0, color, label):
    """Best-of-N's mean points and Gao's best-of-N form fitted to all seeds' points at once, to 1.5 times its last d;
    and the RL form with the seeds' mean alpha and beta, to the mean of the largest d the seeds' fits saw; for one RM
    size."""
    import numpy as np

    tables = [t for _, t in best.get(pairs, {}).values()]
    if tables:
        d, gain = bon_points(np.mean(tables, 0))
        ax.plot(d, g0 + gain, "o", color=color, ms=3, label=f"best-of-N, RM {pairs:,}" if label else None)
        pooled = [bon_points(t) for t in tables]
        params = fit_gao(np.concatenate([p[0] for p in pooled]), np.concatenate([p[1] for p in pooled]), "bon")
        grid = np.linspace(0, 1.5 * d.max(), 100)
        ax.plot(grid, g0 + curve("bon", *params[:2], grid), "--", color=color, lw=1)
    rl = [v for (f, p, _), v in fits.items() if f == "rl" and p == pairs]
    if rl:
        grid = np.linspace(0.01, np.mean([r[4] for r in rl]), 200)
        alpha, beta = np.mean([r[0] for r in rl]), np.mean([r[1] for r in rl])
        label = f"RL fit, β = 0, RM {pairs:,}" if label else None
        ax.plot(grid, g0 + curve("rl", alpha, beta, grid), ":", color=color, lw=1.2, label=label)


def readme_lines(folder, results, reference, full):
    """None: the README's RLHF block is the rlhf family's."""
    return []
