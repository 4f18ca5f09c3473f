"""What happened during training, for the report of a suite of returns: beta over training for the adaptive-KL
runs, and the update's statistics per tenth of training."""

from __future__ import annotations

import statistics

from common import load_script
from reports.base import curve, fmt, save_figure
from results import UPDATE_STATS, load_runs, read_beta, read_updates


def kl_targets(runs):
    """{(env_id, variant, seed): d_targ} for the adaptive-KL runs among `runs`, from each run's command."""
    out, default = {}, None
    for run in runs:
        words = run.meta.get("command", "").split()
        if "ppo_kl_penalty.py" in words and "--no-adaptive-beta" not in words:
            if "--kl-target" in words:
                out[run.env_id, run.variant, run.seed] = float(words[words.index("--kl-target") + 1])
            else:  # the script's own default, read from it
                default = default or load_script("ppo_kl_penalty.py").Args().kl_target
                out[run.env_id, run.variant, run.seed] = default
    return out


def beta_section(folder):
    """For the adaptive-KL rows: beta over training, per env, and how it ends (the last 10% of updates)."""
    runs = {(r.env_id, r.variant, r.seed): r for r in load_runs(folder)}
    targets = kl_targets(runs.values())
    series = {key: rows for key, rows in read_beta(folder).items() if key in targets}
    if not series:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = [
        "",
        "## Beta over training (adaptive KL)",
        "",
        "From the beta each update used (`losses/beta`). The rule halves beta after each update whose KL is below",
        "d_targ / 1.5. As the learning rate anneals linearly to 0, the last updates are too small to reach that,",
        "and beta halves again and again: the halvings column counts the halvings in a row that end each run.",
        "The last two columns bound what the last 10% of the steps did to the score: the mean return of the last",
        "100 episodes at 90% of the steps, and at the end (the run's score), averaged over the seeds.",
        "",
        "| env | setting | seeds | median beta, first 90% of updates | beta at the end"
        " | updates in the last 10% with KL < d_targ / 1.5 | final run of updates with KL < d_targ / 1.5"
        " | score at 90% of the steps | score at the end |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for env in sorted({key[0] for key in series}):
        fig, ax = plt.subplots(figsize=(6, 3.4))
        for (e, variant, seed), rows in sorted(series.items()):
            if e == env:
                ax.plot([r[0] for r in rows], [r[1] for r in rows], lw=1, label=f"{variant} seed {seed}")
        ax.set_yscale("log")
        ax.set_title(f"{env}: beta of the adaptive KL penalty")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("beta")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
        save_figure(fig, folder, f"beta-{env}.png")
        for variant in sorted({key[1] for key in series if key[0] == env}):
            keys = [key for key in sorted(series) if key[:2] == (env, variant)]
            betas, low_kl = [series[key] for key in keys], [targets[key] / 1.5 for key in keys]
            cut = [int(0.9 * len(rows)) for rows in betas]
            early = statistics.mean(
                statistics.median(r[1] for r in rows[:c]) for rows, c in zip(betas, cut, strict=True)
            )
            end = statistics.mean(rows[-1][1] for rows in betas)
            low = statistics.mean(
                statistics.mean(r[2] < kl for r in rows[c:]) for rows, c, kl in zip(betas, cut, low_kl, strict=True)
            )
            streak = [
                next((i for i, r in enumerate(reversed(rows)) if r[2] >= kl), len(rows))
                for rows, kl in zip(betas, low_kl, strict=True)
            ]
            before = statistics.mean(
                curve(runs[key].rows, [0.9 * int(runs[key].meta["global_step"])])[0] for key in keys
            )
            after = statistics.mean(runs[key].score for key in keys)
            lines.append(
                f"| {env} | {variant} | {len(keys)} | {early:.3g} | {end:.3g} | {low:.0%}"
                f" | {', '.join(map(str, streak))} | {fmt(before)} | {fmt(after)} |"
            )
    lines += [""] + [f"![beta, {env}](curves/beta-{env}.png)" for env in sorted({key[0] for key in series})]
    return lines


def updates_section(folder, variants):
    """The update's statistics over training, per env and setting: each run's mean over each tenth of its
    updates, averaged over the seeds, under the return at the end of each tenth. From <folder>/updates/,
    which run.py writes for every run."""
    runs = {(r.env_id, r.variant, r.seed): r for r in load_runs(folder)}
    stats = {}
    for (env_id, variant, seed), rows in read_updates(folder).items():
        if len(rows) >= 10 and (env_id, variant, seed) in runs:
            stats.setdefault((env_id, variant), []).append((runs[env_id, variant, seed], rows))
    if not stats:
        return []
    lines = [
        "",
        "## The updates over training",
        "",
        "The return (the mean of the last 100 episodes) at the end of each tenth of the steps, and under it each",
        "update's statistics as the script logs them (`losses/*`, see the README's Logged metrics) averaged over",
        "that tenth of the updates; each the mean over the seeds (their number in brackets). An explained variance",
        "below 0 means that the value function predicts the batch's returns worse than their mean does, so that the",
        "advantages are mostly its error.",
        "",
        "| env | setting | statistic | " + " | ".join(f"{10 * i}–{10 * i + 10}%" for i in range(10)) + " |",
        "|---" * 13 + "|",
    ]
    order = {v: i for i, v in enumerate(variants)}
    for env, variant in sorted(stats, key=lambda key: (key[0], order.get(key[1], len(order)), key[1])):
        pairs = stats[env, variant]
        returns = [
            statistics.mean(curve(run.rows, [int(run.meta["global_step"]) * (i + 1) / 10])[0] for run, _ in pairs)
            for i in range(10)
        ]
        lines.append(f"| {env} | {variant} ({len(pairs)}) | return | " + " | ".join(fmt(x) for x in returns) + " |")
        for j, name in enumerate(UPDATE_STATS, start=1):
            tenths = [
                statistics.mean(
                    statistics.mean(r[j] for r in rows[len(rows) * i // 10 : len(rows) * (i + 1) // 10])
                    for _, rows in pairs
                )
                for i in range(10)
            ]
            lines.append(
                f"| {env} | {variant} ({len(pairs)}) | {name} | " + " | ".join(f"{x:.3g}" for x in tenths) + " |"
            )
    return lines
