"""What tests/test_torchrun.py runs under torchrun, one process a rank. Not a test module itself.

    torchrun --nproc-per-node 2 tests/ranks_worker.py update SCRIPT OUT   # one update, each rank on its half
    torchrun --nproc-per-node 2 tests/ranks_worker.py main SCRIPT OUT -- FLAGS...   # the script's main(), as a user

`update` builds one fixed rollout batch (the same on every rank, from a fixed seed), gives rank r its half (rows
r B/2, ..., r B/2 + B/2 - 1), and runs K epochs of the script's own minibatch_loss and gradient step on it, each rank
taking its half of every minibatch; it also feeds each rank's half of a stream of observations to the script's
RunningMeanStd and merges them. `main` runs the script's main() and keeps the agent its train() returns, the KL that
each call of the script's KL rule (Table 4's step size, §4's beta) read, the seeds its envs were reset with, and the
names of the threads still running after main() returned. Both write each rank's weights (and statistics) to
OUT.rank<r>.pt.
"""

import gc
import os
import sys
from pathlib import Path

import torch
import torch.distributed as dist

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from conftest import load_script  # noqa: E402

B, M, K = 64, 16, 2  # the batch, the (global) minibatch, the epochs


def fixed_batch(module, script, seed=0):
    """A rollout batch of B steps for the script's Agent, and an Agent, both from `seed`: the same in every process."""
    torch.manual_seed(seed)
    if script == "ppo_atari.py":
        agent = module.Agent(4)
        obs = torch.randint(0, 256, (B, 4, 84, 84), dtype=torch.uint8)
    else:
        agent = module.Agent(5, 2)
        obs = torch.randn(B, 5)
    with torch.no_grad():
        actions, logprobs, _, values = agent.get_action_and_value(obs)
    batch = dict(obs=obs, actions=actions, logprobs=logprobs + 0.1 * torch.randn(B), values=values)
    batch["advantages"] = torch.randn(B) * 3 + 1
    batch["returns"] = batch["advantages"] + values
    if script == "ppo_kl_penalty.py":
        with torch.no_grad():
            batch["old_means"] = agent.actor_mean(obs) + 0.05 * torch.randn(B, 2)
    return agent, batch


def minibatches(rank, size, epoch):
    """Rank `rank`'s indices (into its half) for each minibatch of one epoch, and the global indices of each
    whole minibatch: every rank's shuffle of its own half, cut into M / size pieces."""
    generator = torch.Generator().manual_seed(100 + epoch)
    shuffles = [torch.randperm(B // size, generator=generator) for _ in range(size)]  # every rank's, in rank order
    local = list(shuffles[rank].split(M // size))
    whole = [
        torch.cat([r * (B // size) + s.split(M // size)[j] for r, s in enumerate(shuffles)]) for j in range(len(local))
    ]
    return local, whole


def update(module, script, agent, batch, rank, size, indices):
    """K epochs of the script's minibatch_loss and the gradient step of its train(), whose average_gradients meets
    the other ranks; `indices(epoch)` gives the minibatches."""
    args = module.Args(ent_coef=0.01, clip_coef=0.2)
    optimizer = torch.optim.Adam(agent.parameters(), lr=1e-4, eps=1e-5)
    extra = (agent.actor_logstd.detach().clone(), torch.tensor(0.5)) if script == "ppo_kl_penalty.py" else ()
    for epoch in range(K):
        for mb_inds in indices(epoch):
            if script == "ppo_atari.py":  # its L^CLIP's clip range, annealed in train(), comes before args
                loss, _ = module.minibatch_loss(agent, batch, mb_inds, torch.tensor(0.2), args)
            else:
                loss, _ = module.minibatch_loss(agent, batch, mb_inds, args, *extra)
            optimizer.zero_grad()
            loss.backward()
            module.average_gradients(agent)
            torch.nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
    return agent


def observations(step, size, rank):
    """The raw observations of rank `rank`'s envs at a step: 4 envs in all, 7-dimensional, far from mean 0, var 1."""
    generator = torch.Generator().manual_seed(1000 + step)
    every_env = (torch.randn(4, 7, generator=generator, dtype=torch.float64) * 5 + 30).numpy()
    return every_env[rank * 4 // size : (rank + 1) * 4 // size]


def main():
    mode, script, out = sys.argv[1:4]
    module = load_script(script)
    if mode == "update":
        dist.init_process_group("gloo")
        rank, size = dist.get_rank(), dist.get_world_size()
        agent, batch = fixed_batch(module, script)
        half = {key: value[rank * B // size : (rank + 1) * B // size] for key, value in batch.items()}
        update(module, script, agent, half, rank, size, lambda epoch: minibatches(rank, size, epoch)[0])
        result = {"agent": agent.state_dict()}
        if hasattr(module, "RunningMeanStd"):
            rms = module.RunningMeanStd((7,))
            for step in range(12):
                rms.update(observations(step, size, rank))
                if step % 5 == 4:  # merged after some rollouts, and the last steps left for a final merge
                    rms.merge_ranks()
            rms.merge_ranks()
            result["rms"] = (rms.mean, rms.var, rms.count)
    else:
        import gymnasium as gym

        agents, episodes, kls, seeds = [], [], [], []
        for rule in ("kl_adaptive_lr", "adapt_beta"):  # (value, kl, target): record the KL, then apply the rule
            if hasattr(module, rule):
                apply = getattr(module, rule)
                setattr(
                    module, rule, lambda value, kl, target, apply=apply: (kls.append(kl), apply(value, kl, target))[1]
                )
        vector_envs = [gym.vector.SyncVectorEnv]
        if script == "ppo_atari.py":
            import ale_py

            vector_envs.append(ale_py.AtariVectorEnv)
        for vector_env in vector_envs:  # record the seeds of each reset that has them, as a list of ints
            reset = vector_env.reset
            vector_env.reset = lambda self, reset=reset, **kw: (
                seeds.append([int(seed) for seed in kw["seed"]]) if kw.get("seed") is not None else None,
                reset(self, **kw),
            )[1]
        make_agent = module.Agent.__init__
        module.Agent.__init__ = lambda self, *a, **k: (make_agent(self, *a, **k), agents.append(self))[0]
        count_episodes = module.Log.episodes
        module.Log.episodes = lambda self, r, ended, s: (
            episodes.append(int(ended.sum())),
            count_episodes(self, r, ended, s),
        )[1]
        sys.argv = [script, *sys.argv[sys.argv.index("--") + 1 :]]
        try:
            module.main()
            code = 0
        except SystemExit as e:
            code = e.code
        rank = int(os.environ["RANK"])  # main() has left the process group
        result = {"agent": agents[-1].state_dict(), "exit": code, "episodes": sum(episodes), "kls": kls, "seeds": seeds}
        gc.collect()  # what is left of the run once main() has returned: the OS threads still running (Linux)
        tasks = Path("/proc/self/task")
        result["threads"] = [(t / "comm").read_text().strip() for t in tasks.iterdir()] if tasks.is_dir() else None
        torch.save(result, f"{out}.rank{rank}.pt")
        sys.exit(code)
    torch.save(result, f"{out}.rank{rank}.pt")
    dist.destroy_process_group()


if __name__ == "__main__":
    main()
