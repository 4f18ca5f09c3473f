"""The rlhf-long report's answer to (h): does a reward model that keeps learning on the policy's own text
(ppo_rlhf.py --rm-refresh K: every K iterations, pairs of the policy's responses to one prompt, labelled by gold as
stage 2's were) remove the fall, and at what cost in labels? Set beside the same reward model left as stage 2 made it,
the KL leash and the ensembles, and, at about equal comparisons, a reward model fitted once to four times the pairs."""

from __future__ import annotations

from common import load_script
from reports.overoptimization_claims import verdict
from reports.overoptimization_measures import (
    SUITE,
    WINDOW,
    beta_of,
    cell,
    end,
    ensemble_of,
    fell_of,
    peak_of,
    refresh_of,
    reward_of,
    rm_pairs,
)
from results import load_runs
from suites import SUITES


def unrefreshed(variant):
    """The suite's variant with a refreshed arm's flags but --rm-refresh K: the same reward model, never refreshed."""
    flags = SUITES[SUITE].variants[variant][1]
    at = flags.index("--rm-refresh")
    plain = flags[:at] + flags[at + 2 :]
    return next((v for v, (_, f) in SUITES[SUITE].variants.items() if f == plain), None)


def drawn(variant, steps):
    """The comparisons a variant's reward model asked gold for, in a run of `steps` responses: stage 2's --rm-pairs
    (ties and the held-out tenth among them), and a batch of pairs at each refresh; None for a process RM, whose
    labels are its clauses'."""
    if reward_of(variant) == "process":
        return None
    batch = load_script("ppo_rlhf.py").Args().batch_size
    every = refresh_of(variant)
    return rm_pairs(variant) + (steps // batch // every * batch if every else 0)


def used(meta):
    """The labels a run's reward model learned from, from its CSV header: stage 2's (a process RM's clauses, else
    its training pairs) and the refreshes'; None where the header does not say."""
    first = meta.get("rm_clause_labels", meta.get("rm_train_pairs"))
    return None if first is None else int(first) + int(meta.get("rm_refresh_labels", 0))


def refresh_lines(folder, series, sft_of):
    """(h), as report lines: a table of the refreshed arms beside the arms they are set against, and a sentence per
    refreshed arm on the seeds whose fall it removed."""
    refreshed = [v for v in SUITES[SUITE].variants if refresh_of(v) and any(k[0] == v for k in series)]
    if not refreshed:
        return []
    others = [unrefreshed(v) for v in refreshed]
    others += [v for v in SUITES[SUITE].variants if v in ("beta0.05", "rm16384-beta0") or ensemble_of(v) > 1]
    others = [v for v in dict.fromkeys(others) if v and not v.endswith("-same-head")]
    meta = {(r.variant, r.seed): r.meta for r in load_runs(folder)}
    fell = fell_of(series)
    lines = [
        "",
        "| setting | reward model | β | comparisons drawn | labels it learned from | over-optimized | peak gold |"
        " gold at the end |",
        "|---" * 8 + "|",
    ]
    for variant in refreshed + others:
        keys = sorted(k for k in series if k[0] == variant)
        if not keys:
            continue
        counts = {drawn(variant, int(meta[k]["global_step"])) for k in keys if k in meta}
        labels = [n for n in (used(meta.get(k, {})) for k in keys) if n is not None]
        kind = reward_of(variant) + (f" × {ensemble_of(variant)}" if ensemble_of(variant) > 1 else "")
        kind += f", refreshed every {refresh_of(variant)} iterations" if refresh_of(variant) else ""
        lines.append(
            f"| {variant} | {kind} | {beta_of(variant):g} | "
            + (", ".join(f"{n:,}" for n in sorted(counts)) if None not in counts and counts else "–")
            + f" | {cell(labels) if labels else '–'} | {sum(k in fell for k in keys)} of {len(keys)} |"
            f" {cell([peak_of(series[k], sft_of[k])[0] + sft_of[k] for k in keys])} |"
            f" {cell([end(series[k], 'gold_score') for k in keys])} |"
        )
    answers = []
    for variant, plain in zip(refreshed, [unrefreshed(v) for v in refreshed], strict=True):
        seeds = sorted(s for v, s in series if v == variant and (plain, s) in series)
        if not seeds:
            continue
        before = [s for s in seeds if (plain, s) in fell]
        kept = [s for s in before if (variant, s) not in fell]
        gap = [end(series[variant, s], "gold_score") - end(series[plain, s], "gold_score") for s in seeds]
        answers.append(
            f"`{variant}` fell in {sum((variant, s) in fell for s in seeds)} of {len(seeds)} seeds, `{plain}` in"
            f" {len(before)}; of those, the refresh kept {len(kept)} from falling"
            + (f" (seed {', '.join(map(str, kept))})" if kept else "")
            + f", and its gold at the end is {verdict(gap, 'the unrefreshed run')}"
        )
    return [
        "- **(h) Does a reward model that keeps learning on the policy's own text remove the fall, and at what cost in"
        " labels?** (Bai et al. 2022's iterated online RLHF; Llama 2's reward models, retrained on each new policy's"
        " samples. Every K iterations, pairs of the policy's current responses to one prompt are labelled by the gold"
        " comparisons, or a process RM's clauses by their gold, that labelled stage 2's data, and the reward model"
        " trains on them for a few steps. A refreshed run is judged on its gold and its KL alone: its reward model's"
        " score at the end is a later model's than the one that scored the peak, so whether that score held is not"
        " asked.) "
        + ("; ".join(answers) + "." if answers else "No refreshed run has its unrefreshed run beside it.")
        + " The table sets them beside the KL leash, the ensembles, and a reward model fitted once to more pairs: the"
        " comparisons drawn are those gold was asked for (ties and the held-out tenth among them), stage 2's and the"
        " refreshes' together, so that arms that drew about as many compare at about equal labels; the labels learned"
        " from are the pairs trained on, or a process RM's clause labels, where the run's CSV records them. Peak and"
        f" end: the means of {WINDOW}-iteration windows, as above; mean ± std over seeds.",
        *lines,
    ]
