"""The paper's Figure 2, from one real first update of ppo_continuous.py on Hopper-v5.

    python benchmarks/figure2.py            # writes benchmarks/results/figure2/figure2.{csv,png}

Figure 2 of the paper interpolates the policy's parameters from theta_old to the theta that the
first PPO update produced, theta(a) = theta_old + a (theta - theta_old), and plots over a:
- L^CPI(a) = E[r A], the unclipped surrogate (eq. 6);
- E[clip(r, 1 - eps, 1 + eps) A], the clipped term alone;
- L^CLIP(a) = E[min(r A, clip(r, 1 - eps, 1 + eps) A)] (eq. 7), a lower bound of L^CPI;
- E[KL[pi_old, pi_theta(a)]], on a second axis.
Here a runs past the update, to 2, to show L^CLIP turning down where L^CPI keeps rising.

The update is ppo_continuous.py's own: its train() runs one iteration with the paper's MuJoCo
settings (Table 3), while this script notes the rollout the update learned from (observations,
actions and their log-probs under theta_old) and the advantages that compute_gae returned. The
advantages are normalized over the whole batch here; the update normalized each minibatch.
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import load_script  # noqa: E402
from results import commit, machine, versions  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "figure2"
POLICY = ("actor_mean", "actor_logstd")  # the parameters that interpolate; the value network does not enter


def first_update(**overrides):
    """Run ppo_continuous.py's train() for one iteration. Returns the module, the agent before and after
    the update, the rollout (normalized observations, actions, log-probs under theta_old), the advantages
    and the clip range."""
    import copy

    import torch

    module = load_script("ppo_continuous.py")
    noted = {"obs": [], "actions": [], "logprobs": []}

    class NotingAgent(module.Agent):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            noted["agent"], noted["before"] = self, copy.deepcopy(self)

        def get_action_and_value(self, obs, action=None):
            out = super().get_action_and_value(obs, action)
            if action is None:  # a rollout step (the update passes the batch's actions)
                for key, value in zip(("obs", "actions", "logprobs"), (obs, out[0], out[1]), strict=True):
                    noted[key].append(value.detach().clone())
            return out

    real_gae = module.compute_gae

    def noting_gae(*args, **kwargs):
        noted["advantages"], returns = real_gae(*args, **kwargs)
        return noted["advantages"], returns

    real_agent, module.Agent, module.compute_gae = module.Agent, NotingAgent, noting_gae
    try:
        with tempfile.TemporaryDirectory() as run_dir:
            args = module.Args(**{"env_id": "Hopper-v5", "seed": 1, **overrides, "run_dir": run_dir})
            args.total_timesteps = args.num_envs * args.num_steps  # one iteration: one rollout, one update
            torch.set_num_threads(args.torch_threads)  # as the script's main() sets the process up before train()
            after, _ = module.train(args)
    finally:
        module.Agent, module.compute_gae = real_agent, real_gae
    rollout = {key: torch.cat(noted[key]) for key in ("obs", "actions", "logprobs")}
    return module, noted["before"], after, rollout, noted["advantages"].reshape(-1), args.clip_coef


def interpolate(alphas, **overrides):
    """The four curves of Figure 2 at each interpolation factor: rows of (a, L^CPI, clipped term, L^CLIP, KL)."""
    import torch
    from torch.distributions import Normal, kl_divergence

    _, before, after, rollout, advantages, eps = first_update(**overrides)
    advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    # old is a copy: loading writes in place
    old = {k: v.clone() for k, v in before.state_dict().items() if k.startswith(POLICY)}
    new = {k: v for k, v in after.state_dict().items() if k.startswith(POLICY)}
    with torch.no_grad():
        pi_old = Normal(before.actor_mean(rollout["obs"]), before.actor_logstd.exp())
        rows = []
        for a in alphas:
            before.load_state_dict({k: old[k] + a * (new[k] - old[k]) for k in old}, strict=False)
            pi = Normal(before.actor_mean(rollout["obs"]), before.actor_logstd.exp())
            ratio = (pi.log_prob(rollout["actions"]).sum(-1) - rollout["logprobs"]).exp()
            clipped = ratio.clamp(1 - eps, 1 + eps) * advantages
            rows.append(
                (
                    float(a),
                    (ratio * advantages).mean().item(),
                    clipped.mean().item(),
                    torch.min(ratio * advantages, clipped).mean().item(),
                    kl_divergence(pi_old, pi).sum(-1).mean().item(),
                )
            )
        before.load_state_dict(old, strict=False)
    return rows


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a, cpi, clip_term, clip, kl = zip(*rows, strict=True)
    fig, ax = plt.subplots(figsize=(6, 3.8))
    ax.plot(a, cpi, label="$L^{CPI}$ = E[r A]")
    ax.plot(a, clip_term, label="E[clip(r, 1-ε, 1+ε) A]")
    ax.plot(a, clip, label="$L^{CLIP}$ = E[min(r A, clip(r, 1-ε, 1+ε) A)]", lw=2)
    ax.axvline(1.0, color="gray", ls=":", lw=1)
    ax.set_xlabel("linear interpolation factor (0: θ_old, 1: θ after the first update)")
    ax.set_ylabel("surrogate objective")
    kl_ax = ax.twinx()
    kl_ax.plot(a, kl, color="tab:red", ls="--", label="E[KL[π_old, π_θ]]")
    kl_ax.set_ylabel("mean KL", color="tab:red")
    lines = ax.get_legend_handles_labels()[0] + kl_ax.get_legend_handles_labels()[0]
    ax.legend(lines, [line.get_label() for line in lines], fontsize=7, loc="upper left")
    ax.set_title("Figure 2, Hopper-v5: the first update of ppo_continuous.py")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-alpha", type=float, default=2.0, help="interpolate from 0 to this (1 is the update)")
    parser.add_argument("--points", type=int, default=81)
    args = parser.parse_args()
    alphas = [args.max_alpha * i / (args.points - 1) for i in range(args.points)]
    rows = interpolate(alphas, seed=args.seed)
    OUT.mkdir(parents=True, exist_ok=True)
    with open(OUT / "figure2.csv", "w", newline="") as f:
        f.write(
            f"# command: python benchmarks/figure2.py --seed {args.seed} --max-alpha {args.max_alpha}"
            f" --points {args.points}\n"
        )
        f.write(f"# commit: {commit()}\n# versions: {versions()}\n# machine: {machine()}\n")
        writer = csv.writer(f)
        writer.writerow(["alpha", "L_CPI", "clipped_term", "L_CLIP", "mean_KL"])
        writer.writerows(rows)
    plot(rows, OUT / "figure2.png")
    peak = max(rows, key=lambda row: row[3])
    at_one = min(rows, key=lambda row: abs(row[0] - 1.0))
    print(
        f"wrote {OUT / 'figure2.csv'} and figure2.png: L^CLIP peaks at a = {peak[0]:.2f};"
        f" the update's mean KL is {at_one[4]:.4f}"
    )


if __name__ == "__main__":
    main()
