"""The rlhf family: ppo_rlhf.py's suite. Per setting, each metric's mean over the last tenth of training; per seed,
whether it was over-optimized and by what hack; best-of-N from pi_SFT; the RM and gold scores against sqrt(KL); the
responses each run printed last; and the README's RLHF block."""

from __future__ import annotations

from pathlib import Path

from common import load_script
from reports.base import fmt, ordered_variants, provenance, where_run
from reports.rlhf_series import (
    CLIP,
    MIN_FALL,
    PREVIOUS,
    RULES,
    SMOOTH,
    Z,
    cell,
    direct_variants,
    falls,
    plot_rlhf_seeds,
    tenths,
    without_old_accuracy,
)
from reports.stats import mean_std
from results import (
    BEST_OF_N,
    KTO_STATS,
    RESULTS,
    RLHF_STATS,
    load_runs,
    read_best_of_n,
    read_rlhf_series,
    read_series,
)
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


def kto_lines(folder):
    """report.md's account of KTO's reference point z0 in each --kto run (<folder>/kto/): its range, and that of the
    mismatched pairs' mean implied reward that it clamps at 0, over every minibatch's mean of an iteration."""
    import numpy as np

    series = read_series(folder, "kto")
    if not series:
        return []
    lines = [
        "",
        "## KTO's reference point",
        "",
        "z0 = max(0, the mean implied reward β log(π(y'|x) / π_SFT(y'|x)) of mismatched pairs): each minibatch's own"
        " responses, each after another pair's prompt, as TRL's KTOTrainer builds them. Those responses are π_SFT's"
        " samples, not π's, so their mean estimates about −β KL[π_SFT || π] ≤ 0 where KTO means β KL[π || π_SFT] ≥ 0."
        " Per run, over its iterations (each the mean of its minibatches):",
        "",
        "| setting | seed | z0: min, max | iterations with z0 > 0 | mismatched reward: first tenth, last tenth, min,"
        " max |",
        "|---" * 5 + "|",
    ]
    for (variant, seed), run in sorted(series.items()):
        z0, mismatched = run[:, 1 + KTO_STATS.index("kto_z0")], run[:, 1 + KTO_STATS.index("kto_mismatched_reward")]
        tenth = max(len(run) // 10, 1)
        lines.append(
            f"| {variant} | {seed} | {z0.min():.4f}, {z0.max():.4f} | {int(np.sum(z0 > 0))} of {len(z0)} |"
            f" {mismatched[:tenth].mean():.3f}, {mismatched[-tenth:].mean():.3f}, {mismatched.min():.3f},"
            f" {mismatched.max():.3f} |"
        )
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
        " a prompt), and on held-out pairs of pi_SFT's responses; – for runs whose CSV does not say they measured it so"
        " (those made before commit 605ebaa: their pool held mostly pairs to different prompts). Spam says a clause"
        " twice; garbled text is outside the grammar.",
        "",
        "Per seed, at the end of training (the means of its last tenth; the pool's pairs at the end):",
        "",
        "| setting | seed | RM score | gold score | KL to pi_SFT (nats) | RM accuracy, held out | RM accuracy, recent"
        " (pairs) | spam | garbled | over-optimized | by the previous rule |",
        "|---" * 11 + "|",
    ]
    fell, before = falls(series, direct_variants()), falls(series, direct_variants(), rule=PREVIOUS)
    held_out = {
        (r.variant, r.seed): float(r.meta["rm_held_out_accuracy"]) for r in runs if "rm_held_out_accuracy" in r.meta
    }
    for variant in variants:
        for seed in sorted(seed for v, seed in series if v == variant):
            run = series[(variant, seed)]
            cells = [f"{tenths(run, name)[-1]:.2f}" for name in ("score", "gold_score", "kl")]
            cells.append(f"{held_out[variant, seed]:.2f}" if (variant, seed) in held_out else "–")
            pairs, accuracy = run[-1, 1 + RLHF_STATS.index("rm_pairs")], tenths(run, "rm_accuracy")[-1]
            cells.append(f"{accuracy:.2f} ({pairs:,.0f})" if pairs == pairs else "–")
            cells += [f"{tenths(run, name)[-1]:.2f}" for name in ("spam", "garbled")]
            cells += [fell.get((variant, seed), "no"), "fell" if (variant, seed) in before else "no"]
            lines.append(f"| {variant} | {seed} | " + " | ".join(cells) + " |")
    lines += ["", f"{rule_text()} {BLIND_SPOT}", *kto_lines(folder)]
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


def rule_text():
    """The rule of over-optimization over tenths in words, and how the previous one differed."""
    (previous_z, _) = RULES[PREVIOUS]
    return (
        f"A seed is over-optimized where its gold rose to its peak and fell from there, each by more than {Z:g}"
        f" standard errors of the noise between tenths and by at least {MIN_FALL:g} gold point, while neither the KL"
        f" to π_SFT nor the RM score fell past {Z:g} standard errors of theirs (the RM score not asked of DPO and KTO,"
        " which never see the RM). The noise leaves out the residuals (each tenth against the mean of its neighbours)"
        f" further from their median than {CLIP:g} robust standard deviations, a collapse's among them; the previous"
        " rule counted every residual, so that a collapse inflated the noise that judged it, and asked"
        f" {previous_z:g} standard errors."
    )


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
    # Stages 1 and 2 depend only on the seed: one outcome reward model a seed, whichever setting ran it (a process RM,
    # --reward process, is another network, and the report's table has its own row)
    outcome = [r for r in runs if "rm_held_out_accuracy" in r.meta and "rm_held_out_clause_accuracy" not in r.meta]
    held_out = {r.seed: float(r.meta["rm_held_out_accuracy"]) for r in outcome}
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
    before = falls(series, direct_variants(), rule=PREVIOUS)
    moved = [
        f"{v} seed {seed} {'fell' if (v, seed) in before else 'did not'}" for v, seed in sorted(set(before) ^ set(fell))
    ]
    lines.append(
        "- **Over-optimization** (Gao et al. 2022). Seeds whose gold score, per tenth of training, rose from the first"
        f" tenth to its peak (the best mean of {SMOOTH} tenths in a row) and fell from there to its last {SMOOTH}"
        f" tenths, with the hack that the last tenth shows most: "
        + ", ".join(overoptimized)
        + f". {rule_text()} Under the previous rule, "
        + (", ".join(moved) if moved else "no verdict differed")
        + f". {BLIND_SPOT}"
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
