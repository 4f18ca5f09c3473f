"""PPO with the adaptive KL penalty for continuous control on MuJoCo, in one file.

The KL-penalized objective L^KLPEN of Schulman et al. 2017 (arXiv:1707.06347), §4, eq. (8), with its adaptive beta,
in the same Algorithm 1 and MuJoCo setup as ppo_continuous.py, of which it is a copy with only the objective changed:
`diff ppo_continuous.py ppo_kl_penalty.py` shows what the KL penalty changes. Where the paper is silent we follow "The
37 Implementation Details of PPO" (Huang et al. 2022), cited as "core detail N" (of their 13) and "continuous detail
N" (of their 9 for continuous actions).

    python ppo_kl_penalty.py                                     # adaptive KL, d_targ = 0.01 (Table 1)
    python ppo_kl_penalty.py --kl-target 0.003                   # adaptive KL, d_targ = 0.003
    python ppo_kl_penalty.py --init-beta 3 --no-adaptive-beta    # fixed KL, beta = 3
    python ppo_kl_penalty.py --init-beta 0 --no-adaptive-beta    # no clipping or penalty: L^CPI
"""

import contextlib
import math
import os
import re
import signal
import sys
import tempfile
import time
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
from torch.distributions import Normal

SCRIPT = os.path.basename(__file__)


@dataclass
class Args:
    exp_name: str = SCRIPT[: -len(".py")]  # the experiment's name, part of the run directory's
    seed: int = 1  # seed of torch and of the environments
    device: str = "auto"  # torch device: auto, cpu, cuda, cuda:1, ... (auto: the CPU, where small MLPs run fastest)
    compile: bool = False  # torch.compile the policy step and the minibatch update (slower to start, faster to run)
    torch_threads: int = 1  # torch CPU threads
    run_dir: str | None = None  # where the logs and the checkpoint go (runs/{env_id}__{exp_name}__{seed}__{time})
    # film episodes 0, 1, 8, 27, ... of the first env in training (every 1000th after 1000), and each evaluation episode
    capture_video: bool = False
    # Algorithm: the paper's MuJoCo settings (Table 3) where it gives one, else the implementation detail cited
    env_id: str = "Hopper-v5"  # the id of a gymnasium environment with a Box action space
    total_timesteps: int = 1_000_000  # total agent steps over all envs, rounded down to whole batches (paper: 1M)
    learning_rate: float = 3e-4  # Adam step size (paper: 3e-4)
    num_envs: int = 1  # number of parallel actors N (paper: 1)
    num_steps: int = 2048  # steps per actor in each rollout, the horizon T (paper: 2048)
    anneal_lr: bool = True  # anneal the learning rate linearly to 0 (core detail 4; Table 3 gives a fixed 3e-4)
    gamma: float = 0.99  # discount factor gamma (paper: 0.99)
    gae_lambda: float = 0.95  # GAE lambda (paper: 0.95)
    minibatch_size: int = 64  # minibatch size (paper: 64); must divide --num-envs x --num-steps
    update_epochs: int = 10  # epochs K over each rollout (paper: 10)
    norm_adv: bool = True  # normalize advantages per minibatch (core detail 7)
    clip_coef: float = 0.2  # clip range of the value loss (core detail 9); the policy objective is not clipped here
    kl_target: float = 0.01  # d_targ, the KL per update that adaptive beta aims at (§4; Table 1: 0.003, 0.01, 0.03)
    init_beta: float = 1.0  # the initial KL penalty coefficient beta (§6.1: 1)
    # adapt beta after each update (§4); --no-adaptive-beta keeps it fixed (Table 1's fixed-KL rows)
    adaptive_beta: bool = True
    clip_vloss: bool = True  # clip the value loss around the old values by --clip-coef (core detail 9; not in eq. (9))
    ent_coef: float = 0.0  # entropy bonus coefficient c2 (paper, MuJoCo: no entropy bonus)
    # c1 of eq. (9), on the squared error (V - V_targ)^2; with separate networks it acts only through the gradient clip
    vf_coef: float = 0.25
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
    """Generalized advantage estimation, eq. (11)-(12), over [T, N] tensors.

    next_values[t] is V of the observation that step t reached: after a time-limit truncation, the
    final observation's, which is bootstrapped (Pardo et al. 2018); no advantage flows across an
    episode's end. The returns A + V are the value function's TD(lambda) targets (core detail 5).

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


def gaussian_kl(mean_old, logstd_old, mean_new, logstd_new):
    """KL[pi_old(.|s) || pi_new(.|s)] of eq. (8) between diagonal Gaussians, exact and per sample.

    Per action dimension: log(s_new / s_old) + (s_old^2 + (m_old - m_new)^2) / (2 s_new^2) - 1/2.

    >>> gaussian_kl(torch.zeros(1), torch.zeros(1), torch.ones(1), torch.zeros(1))  # N(0, 1) -> N(1, 1): 1 / 2
    tensor(0.5000)
    """
    var_ratio = torch.exp(2.0 * (logstd_old - logstd_new))
    mean_term = (mean_old - mean_new).pow(2) * torch.exp(-2.0 * logstd_new)
    return (logstd_new - logstd_old + 0.5 * (var_ratio + mean_term) - 0.5).sum(-1)


def kl_penalty_loss(ratio, advantages, kl, beta):
    """Minus L^KLPEN, eq. (8): -E[r A - beta KL[pi_old, pi_theta]]. With beta = 0 it is minus
    the unclipped objective L^CPI, eq. (6), Table 1's "no clipping or penalty" row."""
    return -(ratio * advantages - beta * kl).mean()


def adapt_beta(beta, kl, kl_target):
    """§4, after each update, with d = E[KL] over the batch: halve beta if d < d_targ / 1.5,
    double it if d > d_targ x 1.5. The paper chose 1.5 and 2 heuristically, and found them uncritical.

    >>> adapt_beta(1.0, 0.001, 0.01), adapt_beta(1.0, 0.01, 0.01), adapt_beta(1.0, 0.1, 0.01)
    (0.5, 1.0, 2.0)
    """
    if kl < kl_target / 1.5:
        return beta / 2.0
    if kl > kl_target * 1.5:
        return beta * 2.0
    return beta


def value_loss(newvalue, oldvalue, returns, clip_coef, clip_vloss=True):
    """L^VF of eq. (9), the squared error (V - V_targ)^2 against the returns, optionally clipped (core detail 9).

    The clipped form is not the paper's: the larger of the errors of the new value and of the old
    value moved at most clip_coef towards it."""
    v_loss_unclipped = (newvalue - returns) ** 2
    if not clip_vloss:
        return v_loss_unclipped.mean()
    v_clipped = oldvalue + torch.clamp(newvalue - oldvalue, -clip_coef, clip_coef)
    return torch.max(v_loss_unclipped, (v_clipped - returns) ** 2).mean()


def update_minibatch(agent, optimizer, mb, clip_coef, args, old_logstd, beta):
    """One step of gradient descent on minus eq. (9), with L^KLPEN in place of L^CLIP, for the minibatch `mb`."""
    _, newlogprob, entropy, newvalue = agent.get_action_and_value(mb["obs"], mb["actions"])
    logratio = newlogprob - mb["logprobs"]
    ratio = logratio.exp()  # r_t(theta), eq. (6)
    advantages = mb["advantages"]
    if args.norm_adv:  # core detail 7: normalize the advantages of each minibatch
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    kl = gaussian_kl(mb["old_means"], old_logstd, agent.actor_mean(mb["obs"]), agent.actor_logstd)
    pg_loss = kl_penalty_loss(ratio, advantages, kl, beta)
    v_loss = value_loss(newvalue, mb["values"], mb["returns"], args.clip_coef, args.clip_vloss)
    entropy = entropy.mean()
    loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss  # minus eq. (9), to minimize (core detail 10)
    optimizer.zero_grad()
    loss.backward()
    if args.clip_grad_norm:  # core detail 11: clip the global norm of all gradients together
        nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
    optimizer.step()
    # Core detail 12: approx_kl is the (r - 1) - log r estimator of KL[pi_old, pi_theta], never negative; nothing is
    # clipped here: clipfrac is the fraction of ratios that PPO-Clip would clip.
    stats = {
        "policy_loss": pg_loss,
        "value_loss": v_loss,
        "entropy": entropy,
        "old_approx_kl": (-logratio).mean(),
        "approx_kl": ((ratio - 1) - logratio).mean(),
        "clipfrac": ((ratio - 1.0).abs() > clip_coef).float().mean(),
        "loss": loss,
    }
    return {name: stat.detach() for name, stat in stats.items()}


# ENVIRONMENT
def make_env(env_id, capture_video=False, video_dir=None, name_prefix="rl-video", episode_trigger=None):
    import gymnasium as gym

    if not capture_video:  # no wrappers: train() clips, normalizes and counts episodes itself
        return gym.make(env_id)
    os.environ.setdefault("MUJOCO_GL", "egl")  # render headless, without a display
    env = gym.make(env_id, render_mode="rgb_array")
    # Film with the model's tracking camera where it has one: a fixed camera loses a walker.
    if "track" in [env.unwrapped.model.camera(i).name for i in range(env.unwrapped.model.ncam)]:
        env = gym.make(env_id, render_mode="rgb_array", camera_name="track")
    return gym.wrappers.RecordVideo(env, video_dir, episode_trigger, name_prefix=name_prefix)


def make_envs(args, video_dir, video_prefix):
    """Core detail 1: N envs stepped together, the first one filmed with --capture-video. SAME_STEP autoreset: the step
    that ends an episode returns the next one's first observation, and the final one in infos["final_obs"]."""
    import gymnasium as gym

    env_fns = [
        lambda i=i: make_env(args.env_id, args.capture_video and i == 0, video_dir, video_prefix)
        for i in range(args.num_envs)
    ]
    return gym.vector.SyncVectorEnv(env_fns, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


# AGENT
def layer_init(layer, std=2**0.5, bias_const=0.0):
    # Core detail 2: orthogonal weights with gain sqrt(2) for hidden layers, constant 0 biases.
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class RunningMeanStd(nn.Module):
    """Running mean and variance of numpy batches [B, *shape] (Chan et al.'s parallel algorithm), kept by
    the agent, not an env wrapper: a checkpoint holds them, and evaluation sees the inputs of training."""

    def __init__(self, shape=(), epsilon=1e-4):
        super().__init__()
        self.mean = np.zeros(shape)
        self.var = np.ones(shape)
        self.count = epsilon

    def update(self, x):
        batch_mean = x.mean(0)
        batch_var = x.var(0)
        batch_count = x.shape[0]
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.var = (
            self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        ) / total
        self.mean = self.mean + delta * batch_count / total
        self.count = total

    def get_extra_state(self):  # nn.Module saves and loads this with the agent's state_dict
        return {"mean": torch.tensor(self.mean), "var": torch.tensor(self.var), "count": self.count}

    def set_extra_state(self, state):
        self.mean = state["mean"].numpy()
        self.var = state["var"].numpy()
        self.count = float(state["count"])


class Agent(nn.Module):
    def __init__(self, obs_dim, act_dim, norm_obs=True):
        super().__init__()
        # Core detail 13 / continuous detail 4: separate 64x64 tanh networks (paper §6.1). Output gains
        # (core detail 2): 1 for the value, 0.01 for the policy mean, so that pi starts near N(0, 1).
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 1), std=1.0),
        )
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, 64)),
            nn.Tanh(),
            layer_init(nn.Linear(64, act_dim), std=0.01),
        )
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

    def get_value(self, obs):
        return self.critic(obs).squeeze(-1)

    def get_action_and_value(self, obs, action=None):
        """A sampled action (or the given one), its log-prob under pi(.|s), the entropy, and V(s)."""
        # Continuous details 1 and 3: a diagonal Gaussian; log-probs sum over the action's dimensions.
        # Its arguments are valid by construction (train() stops if they stop being finite).
        probs = Normal(self.actor_mean(obs), self.actor_logstd.exp(), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(-1), probs.entropy().sum(-1), self.get_value(obs)


# TRAINING
def train(args):
    """Algorithm 1 of §5: N actors collect T steps with pi_theta_old, then K epochs of minibatch updates.

    Returns (agent, run_dir). Raises Stopped after Ctrl-C or SIGTERM, once the checkpoint is saved, and
    Diverged when the loss or the weights stop being finite."""
    from torch.utils.tensorboard import SummaryWriter

    # A new run, or the run of --resume, continued with the hyperparameters of its checkpoint.
    checkpoint = load_checkpoint(args.resume) if args.resume else None
    if checkpoint:
        args = resumed_args(checkpoint, args)
    run_dir = args.run_dir or f"runs/{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    device = pick_device(args.device)
    T, N = args.num_steps, args.num_envs
    batch_size = N * T
    num_iterations = args.total_timesteps // batch_size
    torch.manual_seed(args.seed)  # with the envs' seeds below, all the randomness: on the CPU, one seed gives one run
    with contextlib.ExitStack() as on_exit:  # whatever train() changes or opens is undone or closed on every exit
        stop = on_exit.enter_context(process_settings(args))
        # Videos are named by the step they start from, so that a resumed run overwrites none.
        video_prefix = f"from-step-{checkpoint['global_step'] if checkpoint else 0}"
        envs = make_envs(args, f"{run_dir}/videos", video_prefix)  # core detail 1
        on_exit.callback(envs.close)
        obs_dim = envs.single_observation_space.shape[0]
        act_dim = envs.single_action_space.shape[0]
        agent = Agent(obs_dim, act_dim, norm_obs=args.norm_obs).to(device)
        # Core detail 3: Adam with eps 1e-5. The lr is a tensor: annealing changes a number, not what --compile built.
        lr = torch.tensor(args.learning_rate, device=device)
        optimizer = torch.optim.Adam(agent.parameters(), lr=lr, eps=1e-5, fused=True)
        global_step, start_iteration = restore(checkpoint, agent, optimizer, run_dir)
        beta = checkpoint["beta"] if checkpoint else args.init_beta
        policy = torch.compile(agent.get_action_and_value) if args.compile else agent.get_action_and_value
        update = torch.compile(update_minibatch) if args.compile else update_minibatch

        # Rollout storage: T steps of N envs. Observations are stored normalized: they are the inputs.
        obs = torch.zeros((T, N, obs_dim), device=device)
        actions = torch.zeros((T, N, act_dim), device=device)
        logprobs, rewards, values, terminations, truncations, final_values = torch.zeros((6, T, N), device=device)
        # Env i of run --seed s, from step g on, is seeded (s + g) N + i: two runs from step 0 share no env.
        next_obs, _ = envs.reset(seed=((args.seed + global_step) * N + np.arange(N)).tolist())
        next_obs = torch.as_tensor(agent.normalize_obs(next_obs, update=True), device=device)
        episode_return = np.zeros(N)
        episode_length = np.zeros(N, dtype=np.int64)
        # On --resume, purge_step drops what the run logged after its checkpoint: its curves go on without a fold.
        writer = SummaryWriter(run_dir, purge_step=global_step + 1 if checkpoint else None)
        on_exit.callback(writer.close)
        writer.add_text(
            "hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in asdict(args).items())
        )
        recent_returns = deque(maxlen=100)
        start_time = time.time()
        start_step = global_step
        last_print = 0.0

        # ALGORITHM 1: for iteration = 1, 2, ...
        for iteration in range(start_iteration, num_iterations + 1):
            # Core detail 4: anneal the learning rate linearly to 0; epsilon stays fixed, as in §6.1.
            alpha = 1.0 - (iteration - 1.0) / num_iterations
            optimizer.param_groups[0]["lr"].fill_(alpha * args.learning_rate if args.anneal_lr else args.learning_rate)

            # ROLLOUT: run the policy pi_theta_old in N environments for T timesteps.
            with torch.no_grad():
                for step in range(T):
                    global_step += N
                    obs[step] = next_obs
                    action, logprobs[step], _, values[step] = policy(next_obs)
                    actions[step] = action
                    # Continuous detail 5: clip the action for the env only; the ratio uses the sample's log-prob.
                    action = np.clip(action.cpu().numpy(), envs.single_action_space.low, envs.single_action_space.high)
                    next_obs_raw, reward, term, trunc, infos = envs.step(action)
                    next_obs = torch.as_tensor(agent.normalize_obs(next_obs_raw, update=True), device=device)
                    terminations[step] = torch.as_tensor(term)
                    truncations[step] = torch.as_tensor(trunc)
                    rewards[step] = torch.as_tensor(reward)
                    if args.norm_reward:  # continuous details 8-9
                        rewards[step] = torch.as_tensor(agent.normalize_reward(reward, term | trunc, args.gamma))
                    episode_return += reward
                    episode_length += 1
                    finished = term | trunc  # an episode ended: log its return, the raw rewards' sum
                    for i in np.flatnonzero(trunc):  # the true final observation of an episode cut by the time limit
                        final_obs = agent.normalize_obs(infos["final_obs"][i])
                        final_values[step, i] = agent.get_value(torch.as_tensor(final_obs, device=device))
                    for i in np.flatnonzero(finished):
                        recent_returns.append(episode_return[i])
                        writer.add_scalar("charts/episodic_return", episode_return[i], global_step)
                        writer.add_scalar("charts/episodic_length", episode_length[i], global_step)
                        episode_return[i] = 0.0
                        episode_length[i] = 0

                # ADVANTAGES: next_values[t] = V(s_{t+1}); the last is eq. (10)'s bootstrap V(s_T), and where an
                # episode was truncated, V of its final observation.
                next_values = torch.cat([values[1:], agent.get_value(next_obs)[None]])
                next_values = torch.where(truncations.bool(), final_values, next_values)
                advantages, returns = compute_gae(
                    rewards, values, next_values, terminations, truncations, args.gamma, args.gae_lambda
                )

            # UPDATE: K epochs of minibatch gradient descent on the flattened batch.
            batch = {
                "obs": obs.reshape(-1, obs_dim),
                "actions": actions.reshape(-1, act_dim),
                "logprobs": logprobs.reshape(-1),
                "advantages": advantages.reshape(-1),
                "returns": returns.reshape(-1),
                "values": values.reshape(-1),
            }
            with torch.no_grad():  # pi_old, for the exact KL of eq. (8)
                batch["old_means"] = agent.actor_mean(batch["obs"])
                old_logstd = agent.actor_logstd.clone()
            update_stats = []
            for _epoch in range(args.update_epochs):
                b_inds = torch.randperm(batch_size, device=device)  # core detail 6: a new shuffle each epoch
                for start in range(0, batch_size, args.minibatch_size):
                    mb_inds = b_inds[start : start + args.minibatch_size]
                    mb = {key: value[mb_inds] for key, value in batch.items()}
                    update_stats.append(
                        update(agent, optimizer, mb, args.clip_coef, args, old_logstd, torch.tensor(beta))
                    )

            # ADAPT BETA (§4): d is the exact KL between pi_old and the new policy, over the whole batch.
            with torch.no_grad():
                new_means = agent.actor_mean(batch["obs"])
                kl_batch = gaussian_kl(batch["old_means"], old_logstd, new_means, agent.actor_logstd).mean().item()
            writer.add_scalar("losses/beta", beta, global_step)  # the beta this update used
            writer.add_scalar("losses/kl", kl_batch, global_step)
            if args.adaptive_beta:
                beta = adapt_beta(beta, kl_batch, args.kl_target)

            # LOGGING: the mean over every minibatch of the update, not the last minibatch's value.
            losses = {
                name: torch.stack([stats[name] for stats in update_stats]).mean().item() for name in update_stats[0]
            }
            losses["explained_variance"] = (
                1 - (batch["returns"] - batch["values"]).var() / batch["returns"].var()
            ).item()
            sps = int((global_step - start_step) / (time.time() - start_time))
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"].item(), global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            for name, value in losses.items():
                writer.add_scalar(f"losses/{name}", value, global_step)
            if time.time() - last_print > 10 or iteration == num_iterations:
                last_print = time.time()
                print(progress(global_step, num_iterations * batch_size, sps, recent_returns), flush=True)

            # CHECKPOINT, unless the run diverged: then the last finite checkpoint stays on disk.
            if not (math.isfinite(losses["loss"]) and all(p.isfinite().all() for p in agent.parameters())):
                raise Diverged(
                    f"the loss or the weights are not finite after iteration {iteration}; try a smaller"
                    f" --learning-rate (the last finite checkpoint, if any, is {checkpoint_path})"
                )
            if stop or iteration % args.save_every == 0 or iteration == num_iterations:
                writer.flush()  # the curve on disk reaches at least the checkpoint's step
                save_checkpoint(checkpoint_path, args, agent, optimizer, global_step, iteration, beta)
            if stop:
                raise Stopped(
                    f"saved step {global_step:,} to {checkpoint_path}; continue with --resume {checkpoint_path}"
                )
    print(f"saved {checkpoint_path}")
    return agent, run_dir


# EVALUATION
def evaluate(args):
    """Run the deterministic policy (the Gaussian's mean) of --eval-checkpoint with its saved statistics."""
    checkpoint = load_checkpoint(args.eval_checkpoint)
    train_args = resumed_args(checkpoint, args)
    device = pick_device(args.device)
    env = make_env(train_args.env_id, args.capture_video, f"{train_args.run_dir}/videos-eval", "eval", lambda _: True)
    agent = Agent(env.observation_space.shape[0], env.action_space.shape[0], norm_obs=train_args.norm_obs).to(device)
    agent.load_state_dict(checkpoint["agent"])
    returns = []
    for episode in range(args.eval_episodes):
        raw_obs, _ = env.reset(seed=args.seed + episode)
        done = False
        episode_return = 0.0
        while not done:  # the statistics stay frozen: evaluation does not change the normalization
            with torch.no_grad():
                action = agent.actor_mean(torch.as_tensor(agent.normalize_obs(raw_obs), device=device)).cpu().numpy()
            raw_obs, reward, term, trunc, _ = env.step(np.clip(action, env.action_space.low, env.action_space.high))
            episode_return += float(reward)
            done = term or trunc
        returns.append(episode_return)
    env.close()
    summary = f"return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes"
    print(f"eval {train_args.env_id} step {checkpoint['global_step']:,}: {summary}")
    return returns


# MACHINERY: the process's settings, progress, checkpoints and argument checks.
class Stopped(Exception):
    """Ctrl-C or SIGTERM stopped the run at the end of an iteration, after its checkpoint was saved."""


class Diverged(Exception):
    """The loss or the weights stopped being finite; the last finite checkpoint stays on disk."""


@contextlib.contextmanager
def process_settings(args):
    """Until the run ends, by a return or an error: Ctrl-C and SIGTERM only set a flag, which the loop checks; torch
    uses --torch-threads threads; and with --compile, compiled code samples with torch's generator, as eager code."""
    stop = []
    previous_threads = torch.get_num_threads()
    previous_handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        torch.set_num_threads(args.torch_threads)
        for sig in previous_handlers:
            signal.signal(sig, lambda signum, frame: stop.append(signum))
        with torch._inductor.config.patch(fallback_random=True) if args.compile else contextlib.nullcontext():
            yield stop
    finally:
        torch.set_num_threads(previous_threads)
        for sig, handler in previous_handlers.items():
            signal.signal(sig, handler)


def pick_device(name):
    return torch.device("cpu" if name == "auto" else name)


def progress(global_step, total_steps, sps, recent_returns):
    mean = f"{np.mean(recent_returns):.1f}" if recent_returns else "n/a"
    eta = (total_steps - global_step) / max(sps, 1) / 60
    recent = f"return (last {len(recent_returns)}) {mean}"
    return f"step {global_step:,}/{total_steps:,} | SPS {sps} | {recent} | ETA {eta:.1f} min"


# A resumed run takes its hyperparameters from the checkpoint, and how to run (RUNTIME_FIELDS) from the command line.
RUNTIME_FIELDS = "device compile torch_threads capture_video save_every resume eval_checkpoint eval_episodes".split()
FORMAT = ("ppo-checkpoint-v1", SCRIPT)  # what a checkpoint says it is: a checkpoint of this script
# Flags that must be positive, and flags that must lie in [low, high]. Every float must be finite too.
POSITIVE = "total_timesteps num_envs num_steps minibatch_size update_epochs save_every eval_episodes".split()
POSITIVE += "torch_threads learning_rate clip_coef max_grad_norm kl_target".split()
BOUNDS = {"gamma": (0, 1), "gae_lambda": (0, 1), "vf_coef": (0, math.inf), "ent_coef": (0, math.inf)}
BOUNDS["init_beta"] = (0, math.inf)


def resumed_args(checkpoint, args):
    run_dir = os.path.dirname(os.path.abspath(args.resume or args.eval_checkpoint))
    runtime = {key: getattr(args, key) for key in RUNTIME_FIELDS}
    return Args(**{**checkpoint["args"], **runtime, "run_dir": run_dir})


def restore(checkpoint, agent, optimizer, run_dir):
    """The step and the iteration a run starts from: those after its checkpoint's, whose state it loads, if any."""
    if checkpoint is None:
        return 0, 1
    agent.load_state_dict(checkpoint["agent"])
    optimizer.load_state_dict(checkpoint["optimizer"])
    torch.set_rng_state(checkpoint["torch_rng_state"])
    print(f"resuming {run_dir} at step {checkpoint['global_step']:,} (iteration {checkpoint['iteration']})")
    return checkpoint["global_step"], checkpoint["iteration"] + 1


def save_checkpoint(path, args, agent, optimizer, global_step, iteration, beta):
    # Tensors, numbers and strings, loadable with torch.load(weights_only=True); written, then renamed, atomically.
    checkpoint = {
        "format": FORMAT[0],
        "script": FORMAT[1],
        "args": asdict(args),
        "agent": agent.state_dict(),
        "optimizer": optimizer.state_dict(),
        "global_step": global_step,
        "iteration": iteration,
        "torch_rng_state": torch.get_rng_state(),
        "beta": beta,
    }
    torch.save(checkpoint, f"{path}.tmp")
    os.replace(f"{path}.tmp", path)


def load_checkpoint(path):
    """A checkpoint of this script, loaded on the CPU; a ValueError with a one-line reason if it is not one."""
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"cannot read checkpoint {path!r}: corrupt or not a checkpoint ({type(e).__name__})") from None
    if not isinstance(checkpoint, dict) or (checkpoint.get("format"), checkpoint.get("script")) != FORMAT:
        raise ValueError(f"{path!r} is not a checkpoint written by {SCRIPT}")
    return checkpoint


def check_args(args):
    """Reject bad input before anything heavy loads, with a one-line reason (a ValueError)."""
    for name, value in asdict(args).items():
        flag = "--" + name.replace("_", "-")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{flag} must be a finite number, got {value}")
        if name in POSITIVE and value <= 0:
            raise ValueError(f"{flag} must be positive, got {value}")
        if name in BOUNDS and not BOUNDS[name][0] <= value <= BOUNDS[name][1]:
            raise ValueError(f"{flag} must be in [{BOUNDS[name][0]}, {BOUNDS[name][1]}], got {value}")
    if args.init_beta == 0 and args.adaptive_beta:
        raise ValueError("--init-beta 0 never adapts (halving or doubling 0 leaves 0); add --no-adaptive-beta")
    batch = args.num_envs * args.num_steps
    if batch % args.minibatch_size:
        raise ValueError(f"--minibatch-size {args.minibatch_size} does not divide the batch of {batch} steps")
    if args.resume is None and args.eval_checkpoint is None and args.total_timesteps < batch:
        raise ValueError(f"--total-timesteps {args.total_timesteps} is less than one batch of {batch} steps")
    if args.device not in ("auto", "cpu") and not (args.device.startswith("cuda") and torch.cuda.is_available()):
        raise ValueError(f"--device {args.device} is not available here; use auto or cpu")
    if args.resume is not None or args.eval_checkpoint is not None:
        args = resumed_args(load_checkpoint(args.resume or args.eval_checkpoint), args)
    check_env(args.env_id)
    if args.eval_checkpoint is None:
        check_run_dir(args)


def check_env(env_id):
    import gymnasium as gym

    try:
        env = gym.make(env_id)
    except gym.error.Error as e:
        hint = ". Use ppo_atari.py for Atari games" if re.search(r"ALE/|NoFrameskip|Deterministic", env_id) else ""
        raise ValueError(f"unknown env id {env_id!r}: {e}{hint}") from None
    env.close()
    if not isinstance(env.action_space, gym.spaces.Box) or len(env.observation_space.shape) != 1:
        raise ValueError(
            f"{env_id} has a {env.action_space} action space and {env.observation_space} observations; "
            f"{SCRIPT} needs a Box action space and flat observations. Use ppo_atari.py for Atari"
        )


def check_run_dir(args):
    if args.run_dir is None:
        return
    if os.path.isfile(args.run_dir):
        raise ValueError(f"--run-dir {args.run_dir} is a file, not a directory")
    if args.resume is None and os.path.isdir(args.run_dir) and any("tfevents" in f for f in os.listdir(args.run_dir)):
        raise ValueError(
            f"--run-dir {args.run_dir} already holds a run: continue it with --resume {args.run_dir}/checkpoint.pt,"
            " or pick a new directory"
        )
    try:
        os.makedirs(args.run_dir, exist_ok=True)
        tempfile.TemporaryFile(dir=args.run_dir).close()
    except OSError as e:
        raise ValueError(f"--run-dir {args.run_dir} cannot be created or written: {e.strerror}") from None


def main():
    import tyro

    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        print(f"{SCRIPT}: error: {e}", file=sys.stderr)  # one line, before anything starts
        sys.exit(2)
    try:
        evaluate(args) if args.eval_checkpoint is not None else train(args)
    except Stopped as e:
        print(e)
        sys.exit(130)
    except Diverged as e:
        print(f"{SCRIPT}: error: {e}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
