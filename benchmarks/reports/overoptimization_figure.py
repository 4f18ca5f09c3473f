"""The rlhf-long report's figure: gold against d = sqrt(KL[pi || pi_SFT]) in a panel each for the KL penalty, the group
baselines, DPO, IPO and KTO (the rlhf suite's arms), the RM size, the ensembles, process supervision and the reward
models refreshed on the policy's text, with best-of-N and Gao et al.'s fitted forms."""

from __future__ import annotations

import math
from pathlib import Path

from reports.base import save_figure
from reports.overoptimization_measures import (
    D_BIN,
    DEFAULT_PAIRS,
    SUITE,
    beta_of,
    bon_points,
    curve,
    end,
    ensemble_of,
    one_outcome_rm,
    points,
    refresh_of,
    rm_pairs,
)
from reports.rlhf_series import fit_gao
from results import read_rlhf_series
from suites import SUITES


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
    """<folder>/curves/panels.png: gold against d in a panel each for the KL penalty, the group baselines, DPO, IPO and
    KTO, the RM size, the ensembles and process supervision, with best-of-N and Gao's fitted forms in each, and the
    legends under the panels."""
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
            arms([v for v in SUITES[SUITE].variants if beta_of(v) == 0 and one_outcome_rm(v)], series),
        ),
        (
            f"reward-model ensembles (β = 0, {DEFAULT_PAIRS:,} pairs)",
            arms(["beta0", *(v for v in SUITES[SUITE].variants if ensemble_of(v) > 1)], series),
        ),
        ("process supervision", arms(["beta0", "process-beta0"], series) + arms(["beta0.05", "process"], short)),
    ]
    refreshed = arms([v for v in SUITES[SUITE].variants if refresh_of(v)], series)
    if refreshed:  # the reward models refreshed on the policy's text, beside the same ones never refreshed
        panels.append(
            ("reward models refreshed on π's text (β = 0)", arms(["beta0", "process-beta0"], series) + refreshed)
        )
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
