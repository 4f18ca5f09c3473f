"""The rlhf family: ppo_rlhf.py's suite. Per setting, each metric's mean over the last tenth of training; per seed,
whether it was over-optimized and by what hack; best-of-N from pi_SFT; the RM and gold scores against sqrt(KL); the
responses each run printed last; and the README's RLHF block."""

from __future__ import annotations

import warnings
from pathlib import Path

from common import load_script
from reports.base import fmt, ordered_variants, provenance, save_figure, where_run
from reports.stats import mean_std
from results import BEST_OF_N, RESULTS, RLHF_STATS, load_runs, read_best_of_n, read_rlhf_series
from suites import SUITES

ORDER = 0  # where its suites stand in the READMEs' Results block: by ORDER, then by folder name

# ppo_rlhf.py's suite: what its table shows of each run, the mean over the last tenth of its iterations.
RLHF_COLUMNS = [
    ("score", "RM score"),
    ("gold_score", "gold score"),
    ("kl", "KL to pi_SFT (nats)"),
    ("entropy", "entropy"),
    ("well_formed", "well formed"),
    ("spam", "spam"),
    ("garbled", "garbled"),
    ("eos_fraction", "ends in EOS"),
    ("response_length", "length"),
    ("rm_accuracy", "RM accuracy, recent pairs to one prompt"),
]
BLIND_SPOT = (
    "The spam rule is a blind spot planted in the reward model's data: π_SFT never says a clause twice, so no pair it"
    " learned from ranks a repeat."
)


# From this commit on, the RM's accuracy on the policy's responses counts only recent pairs to one prompt; before it,
# a pool of every rollout's first 16 responses, mostly pairs to different prompts, which the RM never learned to rank.
ONE_PROMPT = "605ebaa"


def without_old_accuracy(series, runs):
    """The series, with the RM's accuracy and its pairs blanked (nan) for runs made before ONE_PROMPT: they measured
    something else under the same name."""
    import subprocess

    import numpy as np

    from results import ROOT

    out = dict(series)
    for run in runs:
        commit = (run.meta.get("commit") or "unknown").split()[0]
        ancestor = subprocess.run(
            ["git", "merge-base", "--is-ancestor", ONE_PROMPT, commit], cwd=ROOT, capture_output=True
        )
        if (run.variant, run.seed) in out and ancestor.returncode != 0:
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
    import numpy as np

    column = run[:, 1 + RLHF_STATS.index(name)]
    width = width or max(1, len(column) // 10)
    first = len(column) % width
    with warnings.catch_warnings():  # an iteration with no pair of different gold has no RM accuracy: nan
        warnings.simplefilter("ignore", RuntimeWarning)
        means = [np.nanmean(column[i : i + width]) for i in range(first, len(column), width)]
        errors = [np.nanstd(column[i : i + width], ddof=1) / np.sqrt(width) for i in range(first, len(column), width)]
    return (means, errors) if spread else means


def direct_variants():
    """The rlhf suite's variants that learn from the preference pairs directly (DPO): the RM plays no part in them."""
    return {variant for variant, (_, flags) in SUITES["rlhf"].variants.items() if "--dpo" in flags}


def falls(series, direct=(), width=None):
    """{(variant, seed): text} for each run over-optimized (Gao et al. 2022). Its gold score, per tenth of training (or
    per `width` iterations), rose from the first to its peak and fell from the peak to the last, each by more than
    twice the standard error of the difference (the run's own noise); its KL to pi_SFT ended above its value at the
    peak; and its RM score ended at least as high as there, but for a variant in `direct` (DPO), which never sees the
    RM: Rafailov et al. (2024) find that direct methods over-optimize too. The text names the hack by the last
    window's shares of spam and garbled text."""
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


def best_of_n_lines(best):
    """report.md's table of best-of-N from pi_SFT: per N, each metric's mean ± std over the seeds' reward models."""
    import numpy as np

    names = [(n, h) for n, h in RLHF_COLUMNS if n in BEST_OF_N[2:-1]]
    names = [("kl", "KL to pi_SFT (nats, at most)"), *names, ("rm_accuracy", "RM accuracy on the kept responses")]
    lines = ["| N | " + " | ".join(heading for _, heading in names) + " |", "|---" * (len(names) + 1) + "|"]
    tables = [table for _, table in best.values()]
    for i, n in enumerate(tables[0][:, 0]):
        cells = []
        for name, _ in names:
            values = [t[i, BEST_OF_N.index(name)] for t in tables if not np.isnan(t[i, BEST_OF_N.index(name)])]
            cells.append(f"{fmt(*mean_std(values))} ({len(values)})" if values else "–")
        lines.append(f"| {n:.0f} | " + " | ".join(cells) + " |")
    return lines


def write_report(folder, runs, reference, results):
    """Write <folder>/report.md and its curves (rlhf_report); returns the markdown."""
    return rlhf_report(Path(folder), runs)


def readme_lines(folder, results, reference, full):
    """None: the rlhf suite is not a table of returns; the README has its own block (rlhf_block)."""
    return []


def rlhf_report(folder, runs):
    """<folder>/report.md for the rlhf suite: per setting, each metric's mean over the last tenth of the iterations,
    then the mean ± std over seeds, and per seed; best-of-N from pi_SFT; <folder>/curves/seeds.png: each seed's RM
    and gold scores against sqrt(KL) (the arms' means, with the fitted forms, are the rlhf-long report's figure); and
    the responses each run printed last."""
    series = without_old_accuracy(read_rlhf_series(folder), runs)
    best = read_best_of_n(folder)
    variants = ordered_variants("rlhf", runs)
    header = "| setting | " + " | ".join(heading for _, heading in RLHF_COLUMNS) + " | RM accuracy, pi_SFT's pairs |"
    lines = [f"# {folder.name}: RLHF on the review language", "", "Generated by `benchmarks/report.py`.", ""]
    lines += [*provenance(runs), "", header, "|---" * (len(RLHF_COLUMNS) + 2) + "|"]
    for variant in variants:
        runs_of = [series[key] for key in sorted(series) if key[0] == variant]
        cells = []
        for name, _ in RLHF_COLUMNS:
            last = [tenths(s, name)[-1] for s in runs_of]
            cells.append(cell(last))
        held_out = [float(r.meta["rm_held_out_accuracy"]) for r in runs if r.variant == variant]
        cells.append(f"{fmt(*mean_std(held_out))} ({len(held_out)})" if held_out else "–")
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Each run's mean over the last tenth of training, as the mean ± std over seeds (n). The reward model's accuracy"
        " is the share of pairs of responses to one prompt, with different gold scores, that it ranks as gold does (the"
        " kind of pair it learned from): among the last 640 responses the policy wrote (nan where it wrote one response"
        f" a prompt), and on held-out pairs of pi_SFT's responses; – for runs made before commit {ONE_PROMPT}, whose"
        " pool held mostly pairs to different prompts. Spam says a clause twice; garbled text is outside the grammar.",
        "",
        "Per seed, at the end of training (the means of its last tenth; the pool's pairs at the end):",
        "",
        "| setting | seed | RM score | gold score | KL to pi_SFT (nats) | RM accuracy, held out | RM accuracy, recent"
        " (pairs) | spam | garbled | over-optimized |",
        "|---" * 10 + "|",
    ]
    fell = falls(series, direct_variants())
    held_out = {r.seed: float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta}
    for variant in variants:
        for seed in sorted(seed for v, seed in series if v == variant):
            run = series[(variant, seed)]
            cells = [f"{tenths(run, name)[-1]:.2f}" for name in ("score", "gold_score", "kl")]
            cells.append(f"{held_out[seed]:.2f}" if seed in held_out else "–")
            pairs, accuracy = run[-1, 1 + RLHF_STATS.index("rm_pairs")], tenths(run, "rm_accuracy")[-1]
            cells.append(f"{accuracy:.2f} ({pairs:,.0f})" if pairs == pairs else "–")
            cells += [f"{tenths(run, name)[-1]:.2f}" for name in ("spam", "garbled")]
            cells.append(fell.get((variant, seed), "no"))
            lines.append(f"| {variant} | {seed} | " + " | ".join(cells) + " |")
    lines += ["", BLIND_SPOT]
    if best:
        meta = [m for m, _ in best.values()]
        wall = sum(float(m.get("wall_time_s", 0)) for m in meta)
        commits = "; ".join(sorted({m.get("commit", "?") for m in meta}))
        lines += [
            "",
            f"## Best-of-N from pi_SFT (seeds {', '.join(map(str, sorted(best)))})",
            "",
            "For each of 256 prompts, N responses of pi_SFT, and the one the seed's reward model scores highest kept:"
            " the frontier of gold against KL that needs no optimizer, with KL[best-of-N || pi_SFT] at most log N -"
            f" (N - 1) / N (Beirami et al. 2024; `benchmarks/best_of_n.py`; commits {commits}; {wall / 60:.1f} min in"
            " all).",
            "",
            *best_of_n_lines(best),
        ]
    lines += [
        "",
        "Gold against sqrt(KL), with best-of-N and Gao et al.'s fitted forms, is drawn for these arms beside the"
        " longer runs in [the rlhf-long report](../rlhf-long/report.md).",
        "",
        "Per seed, the gold score (solid, left axis) and the RM's score (dashed, right axis) against sqrt(KL), each a"
        " moving average over 10 iterations, with the gold score's peak marked:",
        "",
        "![per seed](curves/seeds.png)",
        "",
        "## The responses the reward model scored highest, last printed",
        "",
    ]
    for variant in variants:
        for seed in sorted(seed for v, seed in series if v == variant):
            path = folder / "samples" / f"reviews__{variant}__seed{seed}.txt"
            text = path.read_text().strip() if path.exists() else "(none kept)"
            lines += [f"{variant}, seed {seed}:", "", "```", text, "```", ""]
    plot_rlhf_seeds(folder, series, variants)
    text = "\n".join(lines) + "\n"
    (folder / "report.md").write_text(text)
    return text


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


RLHF_START = "<!-- rlhf: generated by benchmarks/report.py from benchmarks/results/rlhf; do not edit by hand -->"
RLHF_END = "<!-- end of rlhf -->"


def rlhf_block(results=RESULTS):
    """The README's RLHF results: the suite's table in short, what a default run took here, and what the runs say
    about the KL penalty: whether gold fell while the reward model's score held or rose, and the controller's KL."""
    folder = Path(results) / "rlhf"
    runs = load_runs(folder) if folder.is_dir() else []
    if not runs:
        return "\n".join([RLHF_START, "No run of the rlhf suite is committed yet.", RLHF_END])
    finished = {(r.variant, r.seed) for r in runs}
    series = without_old_accuracy({k: s for k, s in read_rlhf_series(folder).items() if k in finished}, runs)
    variants = ordered_variants("rlhf", runs)
    seeds = ", ".join(map(str, sorted({r.seed for r in runs})))
    steps = ", ".join(f"{s:,}" for s in sorted({int(r.meta["global_step"]) for r in runs}))
    columns = [c for c in RLHF_COLUMNS if c[0] in ("score", "gold_score", "kl", "entropy", "spam", "garbled")]
    columns.append(("rm_accuracy", "RM accuracy, recent pairs to one prompt"))
    lines = [
        RLHF_START,
        "",
        f"**`rlhf`: {len(runs)} runs (seeds {seeds}; {steps} responses each)**"
        " ([report, plot and samples](results/rlhf/report.md)): each run's mean over the last tenth of"
        " training, as the mean ± std over seeds:",
        "",
        "| setting | " + " | ".join(heading for _, heading in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    last = {}
    for variant in variants:
        runs_of = {seed: series[(v, seed)] for v, seed in sorted(series) if v == variant}
        last[variant] = {name: [tenths(s, name)[-1] for s in runs_of.values()] for name in RLHF_STATS}
        cells = [cell(last[variant][name], n=False) for name, _ in columns]
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    script = load_script("ppo_rlhf.py").Args()
    # The suite's variant with no flags of its own, at the script's default budget, is `python ppo_rlhf.py`.
    plain = [v for v, (_, flags) in SUITES["rlhf"].variants.items() if not flags]
    default_runs = [r for r in runs if r.variant in plain and int(r.meta["global_step"]) == script.total_episodes]
    minutes = sorted(float(r.meta["wall_time_s"]) / 60 for r in default_runs)
    lines.append("")
    if minutes:
        lines.append(
            f"- **Time.** A default run, `python ppo_rlhf.py`, took {minutes[0]:.1f}–{minutes[-1]:.1f} min for all"
            f" three stages, with {where_run(default_runs)} ({len(minutes)} run{'s' if len(minutes) > 1 else ''};"
            " other work may have shared it)."
        )
    # Stages 1 and 2 depend only on the seed: one reward model a seed, whichever setting ran it.
    held_out = {r.seed: float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta}
    if held_out:
        lines.append(
            f"- **The reward model** ranked {fmt(*mean_std(list(held_out.values())))} of held-out pairs of π_SFT's"
            f" responses as gold does ({len(held_out)} seeds, one reward model each); the table's last column is its"
            " accuracy on pairs of the policy's recent responses to one prompt, where the policy went."
        )
    fell, overoptimized = falls(series, direct_variants()), []
    for variant in variants:
        texts = [f"seed {seed}: {text}" for (v, seed), text in fell.items() if v == variant]
        detail = f" ({'; '.join(texts)})" if texts else ""
        overoptimized.append(f"{variant} {len(texts)} of {len(last[variant]['score'])}{detail}")
    lines.append(
        "- **Over-optimization** (Gao et al. 2022). Seeds whose gold score, per tenth of training, rose to its peak and"
        " fell from it, each by more than twice the run's own standard error, while the KL to π_SFT grew past its"
        " value there and the RM score ended at least as high (for DPO, which never sees the RM, all but the last),"
        " with the hack that the last tenth shows most: " + ", ".join(overoptimized) + f". {BLIND_SPOT}"
    )
    best = read_best_of_n(folder)
    if best:
        import numpy as np

        mean = np.mean([table for _, table in best.values()], axis=0)
        gold, kl = mean[:, BEST_OF_N.index("gold_score")], mean[:, BEST_OF_N.index("kl")]
        lines.append(
            f"- **Best-of-N** from π_SFT, the frontier no optimizer is needed for, reached gold {gold[-1]:.2f} at N ="
            f" {mean[-1, 0]:.0f} (KL at most {kl[-1]:.2f} nats; {gold[0]:.2f} at N = 1), with the reward models"
            f" of seeds {', '.join(map(str, sorted(best)))}."
        )
    long = Path(results) / "rlhf-long"
    if long.is_dir() and load_runs(long):
        from reports.overoptimization import summary_lines

        lines += summary_lines(long, results)
    adaptive = [v for v, (_, flags) in SUITES["rlhf"].variants.items() if flags == ["--adaptive-kl"] and v in last]
    for variant in adaptive:
        lines.append(
            f"- **The controller** held the KL over the last tenth of training at {fmt(*mean_std(last[variant]['kl']))}"
            f" nats, for a target of {script.kl_target:g}, with β there at {fmt(*mean_std(last[variant]['kl_coef']))}."
        )
    return "\n".join(lines + ["", RLHF_END])
