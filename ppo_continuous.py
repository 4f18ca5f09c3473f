# /// script
# requires-python = ">=3.11"
# dependencies = ["torch==2.13.0", "numpy==2.4.6", "gymnasium[mujoco]==1.4.0", "mujoco==4.0.0", "tyro==1.0.17",
#   "tensorboard==2.21.0", "moviepy==2.2.1", "wandb==0.31.0"]
# ///
"""PPO-Clip for continuous control on MuJoCo, in one file.

Proximal Policy Optimization (Schulman et al. 2017, arXiv:1707.06347): the clipped objective L^CLIP of §3, eq. (7),
in Algorithm 1 of §5, with GAE, eq. (11)-(12), and the MuJoCo settings of §6.1-6.2 (Table 3) as defaults. Where the
paper is silent we follow "The 37 Implementation Details of PPO" (Huang et al. 2022), cited as "core detail N" (of
their 13) and "continuous detail N" (of their 9 for continuous actions).

    python ppo_continuous.py                          # Hopper-v5, 1M steps
    python ppo_continuous.py --compile                # the same algorithm, compiled by torch.compile
    torchrun --standalone --nproc-per-node 2 ppo_continuous.py --num-envs 2   # one run in 2 processes, 1 env each
    python ppo_continuous.py --help                   # every flag, with its default
"""

import atexit
import contextlib
import importlib.util
import itertools
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections import deque
from dataclasses import asdict, dataclass
from types import SimpleNamespace

import numpy as np
import torch
import torch._dynamo  # noqa: F401 (before torchrun's process group: see main())
import torch.distributed as dist
import torch.nn as nn
from torch.distributions import Independent, Normal

SCRIPT = os.path.basename(__file__)


@dataclass
class Args:
    exp_name: str = SCRIPT[: -len(".py")]  # the experiment's name, part of the run directory's
    seed: int = 1  # seed of torch and of the environments
    device: str = "auto"  # torch device: auto, cpu, cuda, cuda:1, ... (auto: the CPU, where small MLPs run fastest)
    compile: bool = False  # torch.compile the minibatch update (slower to start, faster to run)
    torch_threads: int = 1  # torch CPU threads
    run_dir: str | None = None  # where the logs and the checkpoint go (runs/{env_id}__{exp_name}__{seed}__{time})
    capture_video: bool = False  # film env 0's episodes 0, 1, 8, 27, ..., 1000, 2000, ... and each evaluation episode
    track: bool = False  # mirror the TensorBoard scalars and the videos to Weights & Biases, as CleanRL's --track
    wandb_project_name: str = "ppo"  # the W&B project of a --track run
    wandb_entity: str | None = None  # the W&B team or user of a --track run (None: your default entity)
    # Algorithm: the paper's MuJoCo settings (Table 3) where it gives one, else the implementation detail cited
    env_id: str = "Hopper-v5"  # the id of a gymnasium environment with a Box action space
    total_timesteps: int = 1_000_000  # total agent steps over all envs, rounded down to whole batches (paper: 1M)
    learning_rate: float = 3e-4  # Adam step size (paper: 3e-4)
    num_envs: int = 1  # number of parallel actors N (paper: 1)
    num_steps: int = 2048  # steps per actor in each rollout, the horizon T (paper: 2048)
    anneal_lr: bool = True  # anneal the learning rate linearly to 0 (core detail 4; Table 3 gives a fixed 3e-4)
    lr_target_kl: float | None = None  # Table 4: adapt the lr to each update's KL, toward this (with --no-anneal-lr)
    gamma: float = 0.99  # discount factor gamma (paper: 0.99)
    gae_lambda: float = 0.95  # GAE lambda (paper: 0.95)
    minibatch_size: int = 64  # minibatch size (paper: 64); must divide --num-envs x --num-steps
    update_epochs: int = 10  # epochs K over each rollout (paper: 10)
    norm_adv: bool = True  # normalize advantages per minibatch (core detail 7)
    clip_coef: float = 0.2  # clip range epsilon of L^CLIP (paper: 0.2), also the value loss's
    clip_vloss: bool = True  # clip the value loss around the old values by --clip-coef (core detail 9; not in eq. (9))
    anneal_logstd: tuple[float, float] | None = None  # a log std not learned but annealed linearly (Table 4: -0.7 -1.6)
    ent_coef: float = 0.0  # entropy bonus coefficient c2 (paper, MuJoCo: no entropy bonus)
    vf_coef: float = 0.25  # c1 of eq. (9), CleanRL's 0.5 on half the squared error; felt only in the gradient clip
    clip_grad_norm: bool = True  # clip the global gradient norm (core detail 11)
    max_grad_norm: float = 0.5  # the maximum global gradient norm, when clipping
    norm_obs: bool = True  # normalize observations with running statistics (continuous details 6-7)
    norm_reward: bool = True  # scale rewards by the running std of the discounted return (continuous details 8-9)
    save_every: int = 10  # write the checkpoint every this many iterations (also at the end and on Ctrl-C)
    resume: str | None = None  # continue the run saved in this checkpoint, with the hyperparameters it holds
    eval_checkpoint: str | None = None  # evaluate the deterministic policy of this checkpoint instead of training
    eval_episodes: int = 10  # number of episodes for --eval-checkpoint


# THE MATH
def compute_gae(rewards, values, next_values, terminations, truncations, gamma, gae_lambda):
    """Generalized advantage estimation, eq. (11)-(12), over [T, N] tensors. next_values[t] is V of the observation
    that step t reached: after a time-limit truncation, the final observation's, which is bootstrapped (Pardo et al.
    2018); no advantage flows across an episode's end. The returns A + V are the value function's TD(lambda) targets
    (core detail 5).

    >>> one = torch.ones(3, 1)
    >>> adv, ret = compute_gae(one, 0 * one, 0 * one, torch.tensor([[0.0], [0.0], [1.0]]), 0 * one, 0.5, 1.0)
    >>> adv.flatten().tolist()  # discounted reward-to-go with gamma = 0.5: 1 + .5 + .25, 1 + .5, 1
    [1.75, 1.5, 1.0]
    """
    dones = torch.maximum(terminations.float(), truncations.float())
    terminations = terminations.float()
    # Eq. (12), for all t at once: delta_t = r_t + gamma V(s_{t+1}) - V(s_t), with V = 0 after a termination.
    deltas = rewards + gamma * (1.0 - terminations) * next_values - values
    # Eq. (11), backwards in time: A_t = delta_t + gamma lambda A_{t+1}, restarted where an episode ended.
    advantages = torch.zeros_like(rewards)
    lastgaelam = torch.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        lastgaelam = deltas[t] + gamma * gae_lambda * (1.0 - dones[t]) * lastgaelam
        advantages[t] = lastgaelam
    return advantages, advantages + values


def clipped_surrogate_loss(ratio, advantages, clip_coef):
    """Minus L^CLIP, eq. (7): -E[min(r A, clip(r, 1 - eps, 1 + eps) A)] (core detail 8).

    >>> clipped_surrogate_loss(torch.tensor([1.5, 0.5]), torch.tensor([1.0, 1.0]), 0.2)  # -(1.2 + 0.5) / 2
    tensor(-0.8500)
    """
    surr1 = ratio * advantages
    surr2 = torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef) * advantages
    return -torch.min(surr1, surr2).mean()


def value_loss(newvalue, oldvalue, returns, clip_coef, clip_vloss=True):
    """L^VF of eq. (9), the squared error (V - V_targ)^2 against the returns, optionally clipped (core detail 9). The
    clipped form is not the paper's: the larger of the errors of the new value and of the old value moved at most
    clip_coef towards it."""
    v_loss_unclipped = (newvalue - returns) ** 2
    if not clip_vloss:
        return v_loss_unclipped.mean()
    v_clipped = oldvalue + torch.clamp(newvalue - oldvalue, -clip_coef, clip_coef)
    return torch.max(v_loss_unclipped, (v_clipped - returns) ** 2).mean()


def minibatch_loss(agent, batch, mb_inds, args):
    """Minus L^{CLIP+VF+S}, eq. (9), on the minibatch mb_inds of the batch, and the statistics of its terms."""
    mb = {key: value[mb_inds] for key, value in batch.items()}
    _, newlogprob, probs, newvalue = agent.get_action_and_value(mb["obs"], mb["actions"])
    logratio = newlogprob - mb["logprobs"]
    ratio = logratio.exp()  # r_t(theta), eq. (6)
    advantages = mb["advantages"]
    if args.norm_adv:  # core detail 7: normalize the advantages of each minibatch
        everyone = all_ranks(advantages)  # torchrun: every rank's share of the minibatch; one process: advantages
        advantages = (advantages - everyone.mean()) / (everyone.std() + 1e-8)
    pg_loss = clipped_surrogate_loss(ratio, advantages, args.clip_coef)
    v_loss = value_loss(newvalue, mb["values"], mb["returns"], args.clip_coef, args.clip_vloss)
    entropy = probs.entropy().mean()
    loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss  # minus eq. (9), to minimize (core detail 10)
    stats = {"policy_loss": pg_loss, "value_loss": v_loss, "entropy": entropy}  # each logged as losses/<name>
    # Core detail 12: approx_kl is the (r - 1) - log r estimator of KL[pi_old, pi_theta], never negative.
    stats["old_approx_kl"] = (-logratio).mean()
    stats["approx_kl"] = ((ratio - 1) - logratio).mean()
    stats["clipfrac"] = ((ratio - 1.0).abs() > args.clip_coef).float().mean()
    # train() reads "approx_kl" (--lr-target-kl) and "loss", the loss returned: a term added above is checked and logged
    return loss, {name: stat.detach() for name, stat in (stats | {"loss": loss}).items()}


def linear_anneal(start, end, fraction):
    """Table 4's LinearAnneal(start, end), `fraction` of the way through training: the humanoid's log std (§6.3).
    >>> linear_anneal(-0.7, -1.6, 0.5)
    -1.15
    """
    return start + fraction * (end - start)


def kl_adaptive_lr(lr, kl, target_kl):
    """Table 4's Adam step size, adjusted from the KL of the last update: the paper gives no rule, so this is the one of
    Schulman's policy-gradient code for the Berkeley deep RL course, in [1e-5, 1e-2] as rsl_rl keeps it.
    >>> [kl_adaptive_lr(4.5e-4, kl, target_kl=0.01) for kl in (0.05, 0.01, 0.001)]  # above 2x, near, below 1/2
    [0.0003, 0.00045, 0.000675]
    """
    if kl > 2.0 * target_kl:
        return max(lr / 1.5, 1e-5)
    if kl < target_kl / 2.0:
        return min(lr * 1.5, 1e-2)
    return lr


# TRAINING
def train(args, stop=()):
    """Algorithm 1 of §5: N actors collect T steps with pi_theta_old, then K epochs of minibatch updates. Returns
    (agent, run_dir). Raises Diverged if the loss or weights stop being finite, Stopped after a checkpoint on `stop`."""
    checkpoint, args = load_checkpoint(args.resume, args) if args.resume else (None, args)  # --resume: its args
    run_dir = args.run_dir or new_run_dir(args)
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    global_step = checkpoint["global_step"] if checkpoint else 0
    device = pick_device(args.device)
    T, N = args.num_steps, args.num_envs
    rank, world_size = rank_and_size()
    N_rank = N // world_size  # torchrun: each rank steps its share of the N envs, from env rank x N_rank on
    num_iterations = args.total_timesteps // (N * T)
    compiled_loss = torch.compile(minibatch_loss, fullgraph=True) if args.compile else None  # --compile: backward too
    torch.manual_seed(args.seed)  # with the envs' seeds below, all the randomness: on the CPU, one seed gives one run
    # Videos are named by their first step. On --resume, purge_step drops what the run logged after its checkpoint.
    with (
        contextlib.closing(make_envs(args, f"{run_dir}/videos", f"from-step-{global_step}")) as envs,
        open_writer(run_dir, purge_step=global_step + 1 if checkpoint else None) as writer,
    ):
        obs_dim = envs.single_observation_space.shape[0]
        act_dim = envs.single_action_space.shape[0]
        agent = Agent(obs_dim, act_dim, norm_obs=args.norm_obs).to(device)
        agent.actor_logstd.requires_grad_(args.anneal_logstd is None)  # Table 4: a schedule sets it, not the gradient
        # Core detail 3: Adam with eps 1e-5. The lr is a tensor changed in place: data to compiled code, not a constant.
        lr = torch.tensor(args.learning_rate, device=device)
        optimizer = torch.optim.Adam(agent.parameters(), lr=lr, eps=1e-5, fused=True)
        if checkpoint:  # the weights, Adam's moments and the random state where the checkpoint left them
            agent.load_state_dict(checkpoint["agent"])
            optimizer.load_state_dict(checkpoint["optimizer"])
            torch.set_rng_state(checkpoint["torch_rng_state"])
            print(f"resuming {run_dir} at step {global_step:,}")
        if rank > 0:  # torchrun: the ranks made the same weights; rank r > 0 then draws from a stream of its own
            torch.manual_seed(int(np.random.SeedSequence([args.seed, rank, global_step]).generate_state(1)[0]))

        buf = SimpleNamespace()  # the rollout buffer, T steps of this rank's envs: buf.obs is the update's mb["obs"]
        buf.obs = torch.zeros((T, N_rank, obs_dim), device=device)  # normalized: the network's inputs
        buf.actions = torch.zeros((T, N_rank, act_dim), device=device)
        buf.logprobs = torch.zeros((T, N_rank), device=device)
        buf.values = torch.zeros((T, N_rank), device=device)
        buf.terminations = torch.zeros((T, N_rank), device=device)
        buf.truncations = torch.zeros((T, N_rank), device=device)
        buf.rewards = torch.zeros((T, N_rank), device=device)
        buf.final_values = torch.zeros((T, N_rank), device=device)  # V of the final observation, where a time limit cut
        # Env i of run --seed s, from step g on, is seeded (s + g) N + i: two runs from step 0 share no env.
        next_obs, _ = envs.reset(seed=((args.seed + global_step) * N + rank * N_rank + np.arange(N_rank)).tolist())
        next_obs = torch.as_tensor(agent.normalize_obs(next_obs, update=True), device=device)
        log = Log(writer, args, global_step, num_iterations * N * T)

        # ALGORITHM 1: for iteration = 1, 2, ...
        for iteration in range(checkpoint["iteration"] + 1 if checkpoint else 1, num_iterations + 1):
            # Core detail 4: anneal the learning rate linearly to 0; epsilon stays fixed, as in §6.1.
            alpha = 1.0 - (iteration - 1.0) / num_iterations
            if args.anneal_lr:
                optimizer.param_groups[0]["lr"].fill_(alpha * args.learning_rate)
            if args.anneal_logstd:  # Table 4: the log std follows its schedule (and the lr the KL, after the update)
                agent.actor_logstd.fill_(linear_anneal(*args.anneal_logstd, 1.0 - alpha))

            # ROLLOUT: run the policy pi_theta_old in N environments for T timesteps.
            with torch.inference_mode():
                for step in range(T):
                    global_step += N
                    buf.obs[step] = next_obs
                    action, buf.logprobs[step], _, buf.values[step] = agent.get_action_and_value(next_obs)
                    buf.actions[step] = action
                    # Continuous detail 5: clip the action for the env only; the ratio uses the sample's log-prob.
                    action = np.clip(action.cpu().numpy(), envs.single_action_space.low, envs.single_action_space.high)
                    next_obs_raw, reward, term, trunc, infos = envs.step(action)
                    next_obs = torch.as_tensor(agent.normalize_obs(next_obs_raw, update=True), device=device)
                    buf.terminations[step] = torch.as_tensor(term)
                    buf.truncations[step] = torch.as_tensor(trunc)
                    scaled = agent.normalize_reward(reward, term | trunc, args.gamma) if args.norm_reward else reward
                    buf.rewards[step] = torch.as_tensor(scaled)  # continuous details 8-9: the reward learned
                    for i in np.flatnonzero(trunc):  # the true final observation of an episode cut by the time limit
                        final_obs = torch.as_tensor(agent.normalize_obs(infos["final_obs"][i]), device=device)
                        buf.final_values[step, i] = agent.get_value(final_obs)
                    log.episodes(reward, term | trunc, global_step)  # the raw rewards' sum is an episode's return

                next_value = agent.get_value(next_obs)  # V(s_T), eq. (10)'s bootstrap
            agent.merge_ranks()  # torchrun: every rank's statistics become all ranks'; one process: nothing

            # ADVANTAGES: next_values[t] = V(s_{t+1}), and where an episode was truncated, V of its final observation.
            next_values = torch.cat([buf.values[1:], next_value[None]])
            next_values = torch.where(buf.truncations.bool(), buf.final_values, next_values)
            buf.advantages, buf.returns = compute_gae(
                buf.rewards, buf.values, next_values, buf.terminations, buf.truncations, args.gamma, args.gae_lambda
            )

            # UPDATE: K epochs of minibatch gradient descent on the flattened batch.
            batch = {key: value.flatten(0, 1) for key, value in vars(buf).items()}
            update_stats = []
            for _epoch in range(args.update_epochs):
                # Core detail 6: a new shuffle of the batch each epoch, cut into minibatches (1/P of each per rank).
                for mb_inds in torch.randperm(N_rank * T, device=device).split(args.minibatch_size // world_size):
                    loss, stats = (compiled_loss or minibatch_loss)(agent, batch, mb_inds, args)
                    optimizer.zero_grad()
                    loss.backward()
                    average_gradients(agent)  # torchrun: the mean of the ranks' gradients; one process: nothing
                    if args.clip_grad_norm:  # core detail 11: clip the global norm of all gradients together
                        nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                    optimizer.step()
                    update_stats.append(stats)

            # LOGGING: the mean over every minibatch of the update, not the last minibatch's value.
            losses = {name: torch.stack([s[name] for s in update_stats]).mean() for name in update_stats[0]}
            losses = {name: all_ranks(value[None]).mean().item() for name, value in losses.items()}  # over all ranks
            residual = all_ranks(batch["returns"] - batch["values"])
            losses["explained_variance"] = (1 - residual.var() / all_ranks(batch["returns"]).var()).item()
            log.update(global_step, optimizer.param_groups[0]["lr"].item(), losses)
            if args.lr_target_kl:  # Table 4: the next update's step size, from this one's KL (the mean logged)
                step_size = optimizer.param_groups[0]["lr"]
                step_size.fill_(kl_adaptive_lr(step_size.item(), losses["approx_kl"], args.lr_target_kl))

            # CHECKPOINT, unless the run diverged: then the last finite checkpoint stays on disk.
            if not (math.isfinite(losses["loss"]) and all(p.isfinite().all() for p in agent.parameters())):
                raise Diverged(f"loss or weights not finite after iteration {iteration}")
            stopping = bool(all_ranks(torch.tensor([bool(stop)])).any())  # torchrun: all stop at one iteration
            if stopping or iteration % args.save_every == 0 or iteration == num_iterations:
                writer.flush()  # the curve on disk reaches at least the checkpoint's step
                save_checkpoint(checkpoint_path, args, agent, optimizer, global_step, iteration)
            if stopping:
                raise Stopped(f"saved step {global_step:,}: continue with --resume {checkpoint_path}")
    print(f"saved {checkpoint_path}")
    return agent, run_dir


# AGENT
def layer_init(layer, std=2**0.5, bias_const=0.0):
    # Core detail 2: orthogonal weights with gain sqrt(2) for hidden layers, constant 0 biases.
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


def mlp(n_in, n_out, std):
    hidden = [layer_init(nn.Linear(n_in, 64)), nn.Tanh(), layer_init(nn.Linear(64, 64)), nn.Tanh()]
    return nn.Sequential(*hidden, layer_init(nn.Linear(64, n_out), std=std))


def combine(a, b):
    """The (mean, variance, count) of two sets of data together, from each set's: Chan et al.'s parallel algorithm."""
    mean_a, var_a, count_a = a
    mean_b, var_b, count_b = b
    total = count_a + count_b
    delta = mean_b - mean_a
    m2 = var_a * count_a + var_b * count_b + delta**2 * count_a * count_b / total
    return mean_a + delta * count_b / total, m2 / total, total


class RunningMeanStd(nn.Module):
    """Running mean and variance of numpy batches [B, *shape], kept by the agent, not an env wrapper: a checkpoint holds
    them, and evaluation sees the inputs of training. Under torchrun each rank adds its own envs' batches, and after
    each rollout merge_ranks() gives every rank the statistics of all ranks' data."""

    def __init__(self, shape=(), epsilon=1e-4):
        super().__init__()
        self.mean = np.zeros(shape)
        self.var = np.ones(shape)
        self.count = epsilon
        self.merged = (self.mean, self.var, self.count)  # torchrun: the statistics all ranks had at the last merge,
        self.new = (0.0, 0.0, 0)  # and those of this rank's batches since

    def update(self, x):
        batch = (x.mean(0), x.var(0), x.shape[0])
        self.mean, self.var, self.count = combine((self.mean, self.var, self.count), batch)
        if dist.is_initialized():
            self.new = combine(self.new, batch)

    def merge_ranks(self):
        if dist.is_initialized():
            news = [None] * dist.get_world_size()
            dist.all_gather_object(news, self.new)
            for new in news:  # in rank order, the same on every rank
                self.merged = combine(self.merged, new)
            self.mean, self.var, self.count = self.merged
            self.new = (0.0, 0.0, 0)

    def get_extra_state(self):  # nn.Module saves and loads this with the agent's state_dict
        return {"mean": torch.tensor(self.mean), "var": torch.tensor(self.var), "count": self.count}

    def set_extra_state(self, state):
        self.mean = state["mean"].numpy()
        self.var = state["var"].numpy()
        self.count = float(state["count"])
        self.merged = (self.mean, self.var, self.count)


class Agent(nn.Module):
    def __init__(self, obs_dim, act_dim, norm_obs=True):
        super().__init__()
        # Core detail 13 / continuous detail 4: separate 64x64 tanh networks (paper §6.1). Output gains
        # (core detail 2): 1 for the value, 0.01 for the policy mean, so that pi starts near N(0, 1).
        self.critic = mlp(obs_dim, 1, std=1.0)
        self.actor_mean = mlp(obs_dim, act_dim, std=0.01)
        # Continuous detail 2: a state-independent log std, a learned vector starting at 0 (std 1).
        self.actor_logstd = nn.Parameter(torch.zeros(act_dim))
        self.norm_obs = norm_obs
        self.obs_rms = RunningMeanStd((obs_dim,))  # continuous detail 6
        self.return_rms = RunningMeanStd(())  # continuous detail 8
        self.discounted_return = 0.0  # of each env, in training

    def normalize_obs(self, raw_obs, update=False):
        """Raw numpy observations -> float32 network inputs, first adding them to the statistics if `update`."""
        if not self.norm_obs:
            return raw_obs.astype(np.float32)
        if update:
            self.obs_rms.update(raw_obs)  # continuous detail 6
        # Continuous detail 7: clip the normalized observation to [-10, 10].
        normalized = (raw_obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + 1e-8)
        return np.clip(normalized, -10.0, 10.0).astype(np.float32)

    def normalize_reward(self, reward, done, gamma):
        """Continuous details 8-9: divide the rewards by the running std of the discounted return (no mean is
        subtracted), and clip them to [-10, 10]. `done` marks the envs whose episode ended with this reward."""
        self.discounted_return = self.discounted_return * gamma + reward
        self.return_rms.update(self.discounted_return)
        self.discounted_return[done] = 0.0
        return np.clip(reward / np.sqrt(self.return_rms.var + 1e-8), -10.0, 10.0)

    def merge_ranks(self):
        """torchrun: after each rollout, every rank's statistics become those of all ranks' observations and returns."""
        self.obs_rms.merge_ranks()
        self.return_rms.merge_ranks()

    def get_value(self, obs):
        return self.critic(obs).squeeze(-1)

    def get_action_and_value(self, obs, action=None):
        """An action sampled from pi(.|s) (or the given one), its log-prob, pi(.|s) itself, and V(s)."""
        # Continuous details 1 and 3: a diagonal Gaussian, whose log-probs (and entropy) sum over the action's
        # dimensions. Its arguments are valid by construction (train() stops if they stop being finite).
        probs = Independent(Normal(self.actor_mean(obs), self.actor_logstd.exp(), validate_args=False), 1)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs, self.get_value(obs)


# ENVIRONMENT
def make_env(env_id, capture_video=False, video_dir=None, name_prefix="rl-video", episode_trigger=None):
    import gymnasium as gym

    if not capture_video:  # no wrappers: train() clips, normalizes and counts episodes itself
        return gym.make(env_id)
    os.environ.setdefault("MUJOCO_GL", "egl")  # render headless, without a display
    env = gym.make(env_id, render_mode="rgb_array")
    model = getattr(env.unwrapped, "model", None)  # MuJoCo's: film with its tracking camera, which follows a walker
    if model is not None and "track" in [model.camera(i).name for i in range(model.ncam)]:
        env.close()
        env = gym.make(env_id, render_mode="rgb_array", camera_name="track")
    return gym.wrappers.RecordVideo(env, video_dir, episode_trigger, name_prefix=name_prefix)


def make_envs(args, video_dir, video_prefix):
    """Core detail 1: N envs stepped together, the first one filmed with --capture-video. SAME_STEP autoreset: the step
    that ends an episode returns the next one's first observation, and the final one in infos["final_obs"]."""
    import gymnasium as gym

    rank, world_size = rank_and_size()
    N_rank = args.num_envs // world_size  # torchrun: this rank's share of the N envs, from env rank x N_rank on
    module, _, env_name = args.env_id.rpartition(":")
    if module:  # a module:id, whose module registers the id
        importlib.import_module(module)
    if gym.spec(env_name).vector_entry_point and not args.capture_video:  # the env's own N-env implementation, with
        return gym.make_vec(args.env_id, N_rank, vectorization_mode="vector_entry_point")  # the episodes of N envs
    env_fns = [
        lambda i=i: make_env(args.env_id, args.capture_video and i == 0, video_dir, video_prefix)
        for i in range(rank * N_rank, rank * N_rank + N_rank)
    ]
    return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


# MACHINERY: what running the algorithm takes, and teaches nothing of it. First, many processes: under torchrun, P ranks
# run one Algorithm 1, as the paper's MPI actors did, each stepping N/P of the N envs and taking its share of every
# minibatch. These functions are where the ranks meet; in one process they do nothing.
def rank_and_size():
    """This process's rank and the number P of ranks: (0, 1) without torchrun."""
    return (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)


def all_ranks(x):
    """The tensor x of every rank, concatenated in rank order (so row i of the envs' is env i of the run)."""
    if not dist.is_initialized():
        return x
    parts = [torch.empty_like(x) for _ in range(dist.get_world_size())]
    dist.all_gather(parts, x)
    return torch.cat(parts)


def average_gradients(agent):
    """Each rank's gradient is of its equal share of the minibatch: their mean is the whole minibatch's gradient."""
    grads = [p.grad for p in agent.parameters() if p.grad is not None]
    if dist.is_initialized():
        flat = torch.cat([g.flatten() for g in grads])  # one message, not one for each tensor
        dist.all_reduce(flat)
        for g, mean in zip(grads, flat.split([g.numel() for g in grads]), strict=True):
            g.copy_(mean.view_as(g) / dist.get_world_size())


def evaluate(args):
    """Run the deterministic policy (the Gaussian's mean) of --eval-checkpoint with its saved statistics."""
    checkpoint, train_args = load_checkpoint(args.eval_checkpoint, args)
    device = pick_device(args.device)
    video_dir = f"{train_args.run_dir}/videos-eval"
    with make_env(train_args.env_id, args.capture_video, video_dir, "eval", lambda _: True) as env:
        agent = Agent(env.observation_space.shape[0], env.action_space.shape[0], norm_obs=train_args.norm_obs)
        agent.to(device).load_state_dict(checkpoint["agent"])
        returns = []
        for episode in range(args.eval_episodes):
            raw_obs, _ = env.reset(seed=args.seed + episode)
            done = False
            episode_return = 0.0
            while not done:  # the statistics stay frozen: evaluation does not change the normalization
                with torch.inference_mode():
                    obs = torch.as_tensor(agent.normalize_obs(raw_obs), device=device)
                    action = agent.get_action_and_value(obs)[2].mean  # the mean of pi(.|s), whatever the network
                action = np.clip(action.cpu().numpy(), env.action_space.low, env.action_space.high)
                raw_obs, reward, term, trunc, _ = env.step(action)
                episode_return += float(reward)
                done = term or trunc
            returns.append(episode_return)
    summary = f"return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes"
    print(f"eval {train_args.env_id} step {checkpoint['global_step']:,}: {summary}")
    return returns


# A run ends early Stopped (Ctrl-C or SIGTERM, after a checkpoint) or Diverged (the last finite checkpoint kept).
class Stopped(Exception): ...


class Diverged(Exception): ...


def pick_device(name):
    return torch.device("cpu" if name == "auto" else name)


class NoWriter:
    """The TensorBoard writer of ranks > 0 under torchrun, which writes nothing: rank 0 keeps the run's one record."""

    def __getattr__(self, name):
        return lambda *args, **kwargs: None


def open_writer(run_dir, purge_step):
    """The run's TensorBoard writer on rank 0; on the other ranks of a torchrun run, one that writes nothing."""
    from torch.utils.tensorboard import SummaryWriter

    if rank_and_size()[0] == 0:
        return SummaryWriter(run_dir, purge_step=purge_step)
    return contextlib.nullcontext(NoWriter())


class Log:
    """The run's TensorBoard scalars, and its progress on the console every 10 s and at the end. Under torchrun, each
    rank counts its own envs' episodes, and rank 0 logs those of every rank after each update."""

    def __init__(self, writer, args, global_step, total_steps):
        table = "\n".join(f"|{name}|{value}|" for name, value in asdict(args).items())
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
        self.writer = writer
        self.total_steps = total_steps
        self.start_step = global_step
        self.start_time = time.time()
        self.printed = 0.0
        self.returns = np.zeros(args.num_envs // rank_and_size()[1])  # of this rank's episodes under way, and lengths
        self.lengths = np.zeros(args.num_envs // rank_and_size()[1], dtype=np.int64)
        self.ended = []  # (step, return, length) of the episodes that ended since the last update
        self.recent = deque(maxlen=100)  # the returns of the last 100 episodes

    def episodes(self, reward, ended, step):
        """Add each env's reward to its episode; keep the return and length of those that `ended` with it."""
        self.returns += reward
        self.lengths += 1
        self.ended += [(step, self.returns[i], self.lengths[i]) for i in np.flatnonzero(ended)]
        self.returns[ended] = 0.0
        self.lengths[ended] = 0

    def update(self, step, learning_rate, losses):
        every_rank = [self.ended] * rank_and_size()[1]
        if dist.is_initialized():
            dist.all_gather_object(every_rank, self.ended)
        for episode_step, episode_return, length in sum(every_rank, []):
            self.recent.append(episode_return)
            self.writer.add_scalar("charts/episodic_return", episode_return, episode_step)
            self.writer.add_scalar("charts/episodic_length", length, episode_step)
        self.ended = []
        sps = int((step - self.start_step) / (time.time() - self.start_time))
        self.writer.add_scalar("charts/learning_rate", learning_rate, step)
        self.writer.add_scalar("charts/SPS", sps, step)
        for name, value in losses.items():
            self.writer.add_scalar(f"losses/{name}", value, step)
        if time.time() - self.printed > 10 or step == self.total_steps:
            self.printed = time.time()
            mean = f"{np.mean(self.recent):.1f}" if self.recent else "-"  # the return of the last 100 episodes
            eta = (self.total_steps - step) / max(sps, 1) / 60
            print(f"step {step:,}/{self.total_steps:,} | SPS {sps} | return {mean} | ETA {eta:.1f} min", flush=True)


# Typed with --resume, a runtime flag (how the run goes on, where it logs) applies; any other field of Args is a
# hyperparameter, and refused. A checkpoint names this script as it was published: a renamed copy resumes its own.
RUNTIME_FIELDS = "device compile torch_threads capture_video save_every resume eval_checkpoint eval_episodes".split()
RUNTIME_FIELDS += "run_dir exp_name track wandb_project_name wandb_entity".split()
FORMAT = "ppo-checkpoint-v1"
WRITER = "ppo_continuous.py"


def save_checkpoint(path, args, agent, optimizer, global_step, iteration, **more):
    # Tensors, numbers and strings, loadable with torch.load(weights_only=True); written, then renamed, atomically.
    if rank_and_size()[0] > 0:  # torchrun: rank 0 writes it
        return
    state = {"agent": agent.state_dict(), "optimizer": optimizer.state_dict(), "torch_rng_state": torch.get_rng_state()}
    numbers = {"global_step": global_step, "iteration": iteration, **more}
    torch.save({"format": FORMAT, "script": WRITER, "args": asdict(args), **state, **numbers}, f"{path}.tmp")
    os.replace(f"{path}.tmp", path)


def load_checkpoint(path, args):
    """A checkpoint of this script, on the CPU, and the Args of its run; else a ValueError with a one-line reason."""
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"cannot read checkpoint {path!r}: corrupt or not a checkpoint ({type(e).__name__})") from None
    if not isinstance(checkpoint, dict) or (checkpoint.get("format"), checkpoint.get("script")) != (FORMAT, WRITER):
        raise ValueError(f"{path!r} is not a checkpoint written by {WRITER} or a copy of it")
    unknown = set(checkpoint["args"]) - set(asdict(args))  # a field renamed or removed since the checkpoint
    if unknown:
        raise ValueError(f"{path!r} holds hyperparameters that this script's Args lacks: {sorted(unknown)}")
    runtime = {key: getattr(args, key) for key in RUNTIME_FIELDS}
    run_dir = args.run_dir or os.path.dirname(os.path.abspath(path))  # by default, the checkpoint's folder
    return checkpoint, Args(**{**checkpoint["args"], **runtime, "run_dir": run_dir})


def check_network(model, saved, path):
    """Refuse weights saved by another network, in one line that names the first parameter that differs."""
    shapes = [[f"{k} {list(v.shape)}" for k, v in d.items() if torch.is_tensor(v)] for d in (saved, model.state_dict())]
    for theirs, mine in itertools.zip_longest(*shapes, fillvalue="nothing"):
        if theirs != mine:
            raise ValueError(f"{path!r} holds another network: {theirs} where this script's has {mine}")


# Every number must be finite; these must also be positive, and these lie in ranges. A new flag may be any number.
POSITIVE = "total_timesteps learning_rate num_envs num_steps lr_target_kl minibatch_size update_epochs".split()
POSITIVE += "clip_coef max_grad_norm save_every eval_episodes torch_threads".split()
RANGES = {"gamma": (0, 1), "gae_lambda": (0, 1), "ent_coef": (0, math.inf), "vf_coef": (0, math.inf)}


def check_args(args):
    """Reject bad input before anything heavy loads, with a one-line reason (a ValueError)."""
    import gymnasium as gym

    for name, value in asdict(args).items():
        flag = "--" + name.replace("_", "-")
        low, high = RANGES.get(name, (-math.inf, math.inf))
        if type(value) not in (int, float):  # strings, booleans and None have no range
            continue
        if not math.isfinite(value):
            raise ValueError(f"{flag} must be a finite number, got {value}")
        if name in POSITIVE and value <= 0:
            raise ValueError(f"{flag} must be positive, got {value}")
        if not low <= value <= high:
            raise ValueError(f"{flag} must be in [{low}, {high}], got {value}")
    if args.anneal_logstd and not all(map(math.isfinite, args.anneal_logstd)):
        raise ValueError(f"--anneal-logstd must be two finite numbers, got {args.anneal_logstd}")
    if args.lr_target_kl and args.anneal_lr:
        raise ValueError("--lr-target-kl adapts the learning rate to the KL: add --no-anneal-lr")
    batch = args.num_envs * args.num_steps
    if batch % args.minibatch_size:
        raise ValueError(f"--minibatch-size {args.minibatch_size} does not divide the batch of {batch} steps")
    if not (args.resume or args.eval_checkpoint) and args.total_timesteps < batch:
        raise ValueError(f"--total-timesteps {args.total_timesteps} is less than one batch of {batch} steps")
    if args.device not in ("auto", "cpu") and not (args.device.startswith("cuda") and torch.cuda.is_available()):
        raise ValueError(f"--device {args.device} is not available here; use auto or cpu")
    if args.compile and "WORLD_SIZE" in os.environ:  # the graph would hold the group, and gloo's threads, to the exit
        raise ValueError("--compile is for one process; run torchrun without it")
    if args.resume or args.eval_checkpoint:
        checkpoint, args = load_checkpoint(args.resume or args.eval_checkpoint, args)
    world_size = int(os.environ.get("WORLD_SIZE", 1))  # torchrun's P
    if args.num_envs % world_size or args.minibatch_size % world_size:
        sizes = f"--num-envs {args.num_envs} and --minibatch-size {args.minibatch_size}"
        raise ValueError(f"torchrun's {world_size} processes must divide {sizes}: each takes an equal share")
    try:
        env = gym.make(args.env_id)
    except (gym.error.Error, ImportError) as e:  # an unknown id, or a module:id whose module is not found
        hint = ". Use ppo_atari.py for Atari games" if re.search(r"ALE/|NoFrameskip|Deterministic", args.env_id) else ""
        raise ValueError(f"unknown env id {args.env_id!r}: {e}{hint}") from None
    env.close()
    if not isinstance(env.action_space, gym.spaces.Box) or len(env.observation_space.shape) != 1:
        raise ValueError(f"{SCRIPT} needs a Box action space and flat observations, not {env.action_space}")
    if args.resume or args.eval_checkpoint:  # a copy given another network refuses these weights, before any write
        agent = Agent(env.observation_space.shape[0], env.action_space.shape[0], norm_obs=args.norm_obs)
        check_network(agent, checkpoint["agent"], args.resume or args.eval_checkpoint)
    if args.capture_video and importlib.util.find_spec("moviepy") is None:  # gymnasium's RecordVideo writes with it
        raise ValueError("--capture-video writes its videos with moviepy, which is not installed: pip install moviepy")
    if args.capture_video:  # filming that cannot start stops here: a frame, in a child that runs this file's imports
        gl = os.environ.get("MUJOCO_GL", "egl")  # make_env's choice
        imports = f"import runpy, gymnasium as g; runpy.run_path({__file__!r})"
        frame = f"{imports}; e = g.make({args.env_id!r}, render_mode='rgb_array'); e.reset(); e.render()"
        child = subprocess.run([sys.executable, "-c", frame], env={**os.environ, "MUJOCO_GL": gl}, capture_output=True)
        if child.returncode:
            fix = "install EGL (Debian: apt install libegl1 libgl1-mesa-dri) or set MUJOCO_GL=osmesa or glfw"
            reason = child.stderr.decode().strip().splitlines()[-1]
            raise ValueError(f"--capture-video cannot render with MUJOCO_GL={gl} ({reason}): {fix}")
    run_dir = args.run_dir
    if run_dir is None or args.eval_checkpoint:  # train() makes the default one; evaluation writes only videos
        return
    if os.path.isfile(run_dir):
        raise ValueError(f"--run-dir {run_dir} is a file, not a directory")
    if not args.resume and os.path.isdir(run_dir) and any("tfevents" in f for f in os.listdir(run_dir)):
        raise ValueError(f"--run-dir {run_dir} already holds a run: continue it with --resume {run_dir}/checkpoint.pt")
    try:
        os.makedirs(run_dir, exist_ok=True)
        tempfile.TemporaryFile(dir=run_dir).close()
    except OSError as e:
        raise ValueError(f"--run-dir {run_dir} cannot be created or written: {e.strerror}") from None


def new_run_dir(args):
    """Make runs/{env_id}__{exp_name}__{seed}__{time}, the id without a module: prefix (its colon breaks scp), or, if
    taken, the next free name (...-2, -3, ...), atomically by mkdir. Under torchrun, rank 0 makes it for every rank."""
    base = f"runs/{args.env_id.split(':')[-1]}__{args.exp_name}__{args.seed}__{int(time.time())}"
    name = [base]
    for clash in itertools.count(2) if rank_and_size()[0] == 0 else ():
        with contextlib.suppress(FileExistsError):  # the name is taken: try the next
            os.makedirs(name[0])
            break
        name[0] = f"{base}-{clash}"
    if dist.is_initialized():
        dist.broadcast_object_list(name)
    return name[0]


def start_tracking(args):
    """--track: a Weights & Biases run, named after the run directory so that --resume continues it, mirrors the
    TensorBoard scalars and keeps the videos. With no login or no network it logs offline, for `wandb sync`."""
    import wandb

    name = os.path.basename(os.path.abspath(args.run_dir))  # main() gave a resumed run its checkpoint's args
    init = dict(project=args.wandb_project_name, entity=args.wandb_entity, name=name, id=name, config=asdict(args))
    init |= dict(sync_tensorboard=True, save_code=True, resume="allow")
    try:
        wandb.init(**init)
    except wandb.Error as e:  # no login, or no answer within W&B's timeout: training goes on, logged offline
        print(f"wandb: {e}: logging offline instead, for `wandb sync` to upload", file=sys.stderr)
        wandb.teardown()
        wandb.init(**init, mode="offline")
    videos = os.path.join(os.path.abspath(args.run_dir), "videos", "*.mp4")  # all filmed once the process ends
    atexit.register(wandb.save, videos, base_path=args.run_dir, policy="now")


def main():
    import tyro

    args = tyro.cli(Args)
    try:
        if args.resume:  # the command line read again over the checkpoint's hyperparameters shows what was typed
            saved = load_checkpoint(args.resume, args)[1]
            args = tyro.cli(Args, default=saved)
            typed = [f"--{k.replace('_', '-')} {v}" for k, v in asdict(args).items() if v != getattr(saved, k)]
            if typed:  # never dropped in silence
                raise ValueError(f"{', '.join(typed)}: a resumed run keeps its checkpoint's hyperparameters")
        check_args(args)
    except ValueError as e:
        print(f"{SCRIPT}: error: {e}", file=sys.stderr)  # one line, before anything starts
        sys.exit(2)
    torch.set_num_threads(args.torch_threads)
    if args.eval_checkpoint is not None:
        return evaluate(args)
    if "WORLD_SIZE" in os.environ:  # torchrun: this process is one of the P ranks of one run (one GPU each, with cuda)
        if pick_device(args.device).type == "cuda":
            torch.cuda.set_device(int(os.environ["LOCAL_RANK"]))
        # torch._dynamo is imported at the top, before the group: imported after it (by Adam's first step), it holds
        # the group past destroy_process_group, and gloo's threads, alive as the interpreter exits, can abort the exit.
        dist.init_process_group("cpu:gloo,cuda:nccl" if torch.cuda.is_available() else "gloo")
        if dist.get_rank() > 0:  # rank 0 speaks for the run; the others' errors still reach stderr
            sys.stdout = open(os.devnull, "w")
    if not args.run_dir:  # the run's folder, named once for train() and W&B
        args.run_dir = new_run_dir(args)
    # W&B's run, and its patch of TensorBoard's writer, belong to the process: main() starts them (on rank 0)
    if args.track and rank_and_size()[0] == 0:
        start_tracking(args)
    # A training run owns the process: Ctrl-C and SIGTERM only set the flag that train() reads after each iteration.
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))
    try:
        train(args, stop)
    except Stopped as e:
        print(e)
        sys.exit(130)
    except Diverged as e:  # the advice is main()'s, where the flags are: --resume keeps every hyperparameter
        print(f"{SCRIPT}: error: {e}: start a new run with a smaller --learning-rate", file=sys.stderr)
        sys.exit(1)
    except RuntimeError as e:  # torchrun: another rank died (gloo's or nccl's error), and this one ends in one line
        if not (dist.is_initialized() and (isinstance(e, dist.DistError) or "gloo" in str(e))):
            raise
        print(f"{SCRIPT}: error: rank {dist.get_rank()} lost another rank: {str(e).splitlines()[0]}", file=sys.stderr)
        sys.exit(1)
    finally:
        if dist.is_initialized():  # torchrun: leave the group before exiting, which gloo's threads need
            dist.destroy_process_group()


if __name__ == "__main__":
    main()
