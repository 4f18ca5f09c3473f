"""Best-of-N from pi_SFT (Gao et al. 2022, arXiv:2210.10760, §2): the frontier of gold against KL that needs no
optimizer. For each prompt, N responses of pi_SFT; the one the reward model scores highest is kept. Its KL to pi_SFT
is at most log N - (N - 1) / N nats (Beirami et al. 2024 prove the bound; it is exact for a distribution without
atoms, and here, where pi_SFT repeats a few responses, it is nearly tight), so the curve sits on the same axes as PPO's
and DPO's runs.

    python benchmarks/best_of_n.py benchmarks/runs/rlhf/reviews__beta0.05__seed1    # stages 1-2 of that run's seed

It reads the run's sft.pt and reward_model.pt (stages 1 and 2 depend only on the seed and the reward model's flags,
so any arm with the same reward model serves) and writes benchmarks/results/rlhf/best_of_n/seed<N>.csv (for a reward
model of another --rm-pairs P than the default, benchmarks/results/rlhf-long/rm<P>/best_of_n/seed<N>.csv). An
ensemble arm's reward_model.pt holds its K members: they are loaded as the run loaded them, and the kept response is
the one their aggregate (the run's --rm-ensemble-agg, mean, min or uwo) scores highest, written to
benchmarks/results/rlhf-long/rm<P>-ens<K>-<agg>/best_of_n/seed<N>.csv, beside the single RM's, never over it. A process
reward model (--reward process) scores a response by the sum of its clauses' scores, as its run did, and writes to
benchmarks/results/rlhf-long/rm<P>-process/best_of_n/. The CSV holds N, the analytic KL, and the mean RM score, gold
score and shares of well-formed, spam and garbled text of the kept responses, and how often the RM ranks pairs of them
(to one prompt, of different gold) as gold does; after '# key: value' lines that say where and how it was made.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import load_script  # noqa: E402
from reports.overoptimization_measures import SUITE, best_of_n_folder  # noqa: E402
from results import commit, machine, versions  # noqa: E402

NS = [1, 2, 4, 8, 16, 32, 64]


def analytic_kl(n):
    """log n - (n - 1) / n, in nats: the KL[best-of-n || pi_SFT] that Stiennon et al. 2020 and Gao et al. 2022 give,
    which Beirami et al. 2024 (arXiv:2401.01879) prove is an upper bound, reached when no response has a mass."""
    return math.log(n) - (n - 1) / n


def exact_kl(probs, scores, n):
    """KL[best-of-n || p] of a discrete distribution p over responses with these scores, all distinct: the kept
    response is y with probability F(y)^n - F(y-)^n, F the probability of a score at most y's."""
    order = sorted(range(len(probs)), key=lambda i: scores[i])
    kl, below = 0.0, 0.0
    for i in order:
        kept = (below + probs[i]) ** n - below**n
        kl += kept * math.log(kept / probs[i]) if kept > 0 else 0.0
        below += probs[i]
    return kl


def best_of_n(run_dir, prompts=256, ns=NS, seed=0):
    """Rows (N, KL, score, gold, well_formed, spam, garbled, rm_accuracy) for each N in ns, over the same `prompts`
    prompts: the best of the first N of max(ns) responses to each, as the run's reward model ranks them (an
    ensemble's: by its aggregate)."""
    rlhf = load_script("ppo_rlhf.py")
    checkpoint, args = rlhf.load_checkpoint(str(Path(run_dir) / "sft.pt"), rlhf.Args(), "sft")
    sft = rlhf.new_model(args, "cpu", checkpoint["model"])
    # the reward model's own Args: an ensemble's K members and their aggregate are there, not in sft.pt's
    rm_checkpoint, rm_args = rlhf.load_checkpoint(str(Path(run_dir) / "reward_model.pt"), args, "reward_model")
    kind = rlhf.ProcessRewardModel if rm_args.reward == "process" else rlhf.TinyLM  # a process RM: its clauses' sum
    reward_model = rlhf.new_model(rm_args, "cpu", rm_checkpoint["model"], rm_args.rm_ensemble, kind)
    torch.manual_seed(seed)
    tokens, mask = rlhf.generate(sft, prompts, args.response_length, args.temperature, max(ns))
    with torch.no_grad():
        has_eos = (tokens[:, rlhf.PROMPT_LENGTH :] == rlhf.EOS).any(1)
        scores = torch.where(has_eos, reward_model.score(tokens, mask), args.no_eos_score).view(prompts, max(ns))
    gold, forms = rlhf.gold_scores(tokens, mask)
    rows = []
    for n in ns:
        best = scores[:, :n].argmax(1) + torch.arange(prompts) * max(ns)  # the kept response of each prompt
        row = [n, analytic_kl(n), scores.flatten()[best].mean().item(), gold[best].mean().item()]
        row += [forms[name][best].mean().item() for name in ("well_formed", "spam", "garbled")]
        prompt = tokens[best, 2] * len(rlhf.WORDS) + tokens[best, 4]  # the RM learned from pairs to one prompt
        rows.append(row + [rlhf.pairwise_accuracy(scores.flatten()[best], gold[best], prompt)[0].item()])
    return rows


def default_out(results, rm_args):
    """Where best-of-N of a reward model with these Args goes: the folder of its --rm-pairs for one reward model, and
    for an ensemble or a process RM one of its own, named by its pairs and its members and aggregate or "process", so
    that it never overwrites the single reward model's curve that the reports read."""
    if rm_args.reward == "process":
        return Path(results) / SUITE / f"rm{rm_args.rm_pairs}-process" / "best_of_n"
    if rm_args.rm_ensemble == 1:
        return best_of_n_folder(results, rm_args.rm_pairs) / "best_of_n"
    name = f"rm{rm_args.rm_pairs}-ens{rm_args.rm_ensemble}-{rm_args.rm_ensemble_agg}"
    return Path(results) / SUITE / name / "best_of_n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path, help="a ppo_rlhf.py run directory with sft.pt and reward_model.pt")
    parser.add_argument("--prompts", type=int, default=256, help="prompts, each with max N responses (default 256)")
    parser.add_argument("--out", type=Path, help="default: benchmarks/results/rlhf/best_of_n/seed<N>.csv, or rm<P>/...")
    args = parser.parse_args()
    rlhf = load_script("ppo_rlhf.py")
    try:
        seed = rlhf.load_checkpoint(str(args.run_dir / "sft.pt"), rlhf.Args(), "sft")[1].seed
        rm_args = rlhf.load_checkpoint(str(args.run_dir / "reward_model.pt"), rlhf.Args(), "reward_model")[1]
    except ValueError as e:
        sys.exit(f"best_of_n.py: error: {e}")
    out = args.out or default_out(ROOT / "benchmarks" / "results", rm_args) / f"seed{seed}.csv"
    start = time.time()
    rows = best_of_n(args.run_dir, args.prompts, seed=seed)
    header = {"command": " ".join(["python", *sys.argv]), "commit": commit(["ppo_rlhf.py"], " (script modified)")}
    header |= {
        "versions": versions(("torch", "numpy")),
        "machine": machine(),
        "wall_time_s": f"{time.time() - start:.0f}",
    }
    lines = [f"# {key}: {value}" for key, value in header.items()] + [
        "n,kl,score,gold_score,well_formed,spam,garbled,rm_accuracy"
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines + [",".join(f"{x:.6g}" for x in row) for row in rows]) + "\n")
    for row in rows:
        print(f"N {row[0]:>3}: KL {row[1]:.2f} | RM score {row[2]:+.2f} | gold {row[3]:+.2f} | spam {row[5]:.2f}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
