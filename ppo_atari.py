# /// script
# requires-python = ">=3.11"
# dependencies = ["torch==2.13.0", "numpy==2.4.6", "gymnasium==1.4.0", "ale-py==0.12.1", "tyro==1.0.17",
#   "tensorboard==2.21.0", "imageio==2.38.1", "imageio-ffmpeg==0.8.1", "wandb==0.31.0"]
# ///
"""PPO-Clip for Atari, in one file.

Proximal Policy Optimization (Schulman et al. 2017, arXiv:1707.06347) as §6.4 ran it: a CNN shared by policy and value
in L^{CLIP+VF+S}, eq. (9), 8 actors, and alpha annealing the learning rate and the clip range (Table 5). Where the paper
is silent we follow "The 37 Implementation Details of PPO" (Huang et al. 2022): "core detail N" (of 13) and "atari
detail N" (of 9). `diff ppo_continuous.py ppo_atari.py` shows what Atari changes.

    python ppo_atari.py                                  # Breakout, 10M steps (40M frames): a job for a GPU
    python ppo_atari.py --env-id PongNoFrameskip-v4 --total-timesteps 1000000
    python ppo_atari.py --compile                        # the same algorithm, compiled by torch.compile
    torchrun --standalone --nproc-per-node 2 ppo_atari.py --torch-threads 1   # one run in 2 processes, 4 envs each
    python ppo_atari.py --help                           # every flag, with its default
"""

import atexit
import contextlib
import importlib.util
import itertools
import math
import os
import re
import signal
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
from torch.distributions import Categorical

SCRIPT = os.path.basename(__file__)


@dataclass
class Args:
    exp_name: str = SCRIPT[: -len(".py")]  # the experiment's name, part of the run directory's
    seed: int = 1  # seed of torch and of the environments
    device: str = "auto"  # torch device: auto, cpu, cuda, cuda:1, ... (auto is cuda when there is one)
    compile: bool = False  # torch.compile the minibatch update (slower to start, faster to run)
    torch_threads: int = 2  # torch CPU threads (the CNN's convolutions use a second thread)
    run_dir: str | None = None  # where the logs and the checkpoint go (runs/{env_id}__{exp_name}__{seed}__{time})
    capture_video: bool = False  # film games 0, 1, 8, 27, ... of the first env in training, and every evaluation game
    track: bool = False  # mirror the TensorBoard scalars and the videos to Weights & Biases, as CleanRL's --track
    wandb_project_name: str = "ppo"  # the W&B project of a --track run
    wandb_entity: str | None = None  # the W&B team or user of a --track run (None: your default entity)
    # Algorithm: the paper's Atari settings (Table 5) where it gives one, else the implementation detail cited
    env_id: str = "BreakoutNoFrameskip-v4"  # <Game>NoFrameskip-v4 as in the paper, or ALE/<Game>-v5 (sticky actions)
    total_timesteps: int = 10_000_000  # total agent steps over all envs, rounded down to whole batches (paper: 10M)
    max_episode_frames: int = 108_000  # truncate a game after this many frames of play (30 minutes at 60 Hz)
    # After a lost life, step FIRE in place of the policy's action, trained on (ale-py presses it only as a game starts)
    fire_on_life_loss: bool = False
    learning_rate: float = 2.5e-4  # Adam step size at the start (paper: 2.5e-4 x alpha)
    num_envs: int = 8  # number of parallel actors N (paper: 8)
    num_steps: int = 128  # steps per actor in each rollout, the horizon T (paper: 128)
    anneal_lr: bool = True  # anneal the learning rate with alpha, linearly to 0 (Table 5; core detail 4)
    anneal_clip: bool = True  # anneal the clip range of L^CLIP with alpha, 0.1 x alpha (Table 5)
    gamma: float = 0.99  # discount factor gamma (paper: 0.99)
    gae_lambda: float = 0.95  # GAE lambda (paper: 0.95)
    minibatch_size: int = 256  # minibatch size (paper: 32 x 8 = 256); must divide --num-envs x --num-steps
    update_epochs: int = 3  # epochs K over each rollout (paper: 3)
    norm_adv: bool = True  # normalize advantages per minibatch (core detail 7)
    clip_coef: float = 0.1  # clip range epsilon of L^CLIP at the start (paper: 0.1 x alpha), and the value loss's
    clip_vloss: bool = True  # clip the value loss around the old values by --clip-coef (core detail 9; not in eq. (9))
    ent_coef: float = 0.01  # entropy bonus coefficient c2 (paper: 0.01)
    vf_coef: float = 1.0  # c1 of eq. (9), on the squared error (V - V_targ)^2 (paper: 1)
    clip_grad_norm: bool = True  # clip the global gradient norm (core detail 11)
    max_grad_norm: float = 0.5  # the maximum global gradient norm, when clipping
    save_every: int = 50  # write the checkpoint every this many iterations (also at the end and on Ctrl-C)
    resume: str | None = None  # continue the run saved in this checkpoint, with the hyperparameters it holds
    eval_checkpoint: str | None = None  # evaluate the policy of this checkpoint instead of training
    eval_episodes: int = 10  # number of games for --eval-checkpoint


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


def minibatch_loss(agent, batch, mb_inds, epsilon, args):
    """Minus L^{CLIP+VF+S}, eq. (9), on the minibatch mb_inds of the batch, and the statistics of its terms. epsilon is
    L^CLIP's clip range this iteration, annealed by alpha (Table 5); the value loss keeps --clip-coef."""
    mb = {key: value[mb_inds] for key, value in batch.items()}
    _, newlogprob, probs, newvalue = agent.get_action_and_value(mb["obs"], mb["actions"])
    logratio = newlogprob - mb["logprobs"]
    ratio = logratio.exp()  # r_t(theta), eq. (6)
    advantages = mb["advantages"]
    if args.norm_adv:  # core detail 7: normalize the advantages of each minibatch
        everyone = all_ranks(advantages)  # torchrun: every rank's share of the minibatch; one process: advantages
        advantages = (advantages - everyone.mean()) / (everyone.std() + 1e-8)
    pg_loss = clipped_surrogate_loss(ratio, advantages, epsilon)
    v_loss = value_loss(newvalue, mb["values"], mb["returns"], args.clip_coef, args.clip_vloss)
    entropy = probs.entropy().mean()
    loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss  # minus eq. (9), to minimize (core detail 10)
    stats = {"policy_loss": pg_loss, "value_loss": v_loss, "entropy": entropy}  # each logged as losses/<name>
    # Core detail 12: approx_kl is the (r - 1) - log r estimator of KL[pi_old, pi_theta], never negative.
    stats["old_approx_kl"] = (-logratio).mean()
    stats["approx_kl"] = ((ratio - 1) - logratio).mean()
    stats["clipfrac"] = ((ratio - 1.0).abs() > epsilon).float().mean()
    # train() reads "loss", the loss returned: a term added above is in its check that the run is finite, and logged
    return loss, {name: stat.detach() for name, stat in (stats | {"loss": loss}).items()}


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
    # On --resume, purge_step drops what the run logged after its checkpoint.
    with (
        contextlib.closing(make_envs(args, N_rank)) as envs,
        open_writer(run_dir, purge_step=global_step + 1 if checkpoint else None) as writer,
    ):
        agent = Agent(envs.single_action_space.n).to(device)
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
        buf.obs = torch.zeros((T, N_rank, 4, 84, 84), dtype=torch.uint8, device=device)  # uint8 until the network
        buf.actions = torch.zeros((T, N_rank), dtype=torch.long, device=device)
        buf.logprobs = torch.zeros((T, N_rank), device=device)
        buf.values = torch.zeros((T, N_rank), device=device)
        buf.terminations = torch.zeros((T, N_rank), device=device)
        buf.truncations = torch.zeros((T, N_rank), device=device)
        buf.rewards = torch.zeros((T, N_rank), device=device)
        buf.final_values = torch.zeros((T, N_rank), device=device)  # V of the final observation, where a time limit cut
        # Env i of run --seed s, from step g on, is seeded (s + g) N + i: two runs from step 0 share no env.
        next_obs, infos = envs.reset(seed=(args.seed + global_step) * N + rank * N_rank + np.arange(N_rank))
        next_obs = torch.as_tensor(next_obs, device=device)
        frame_numbers = infos["episode_frame_number"]
        lost_life = np.zeros(N_rank, dtype=bool)
        video = GameVideo(args.env_id, run_dir, frame_numbers[0], film=args.capture_video and rank == 0)
        action_names = [a.name for a in envs.ale.get_action_set()]
        fire = action_names.index("FIRE") if args.fire_on_life_loss and "FIRE" in action_names else None
        log = Log(writer, args, global_step, num_iterations * N * T)

        # ALGORITHM 1: for iteration = 1, 2, ...
        for iteration in range(checkpoint["iteration"] + 1 if checkpoint else 1, num_iterations + 1):
            # §6.4, Table 5: alpha falls linearly from 1 to 0, scaling the lr (core detail 4) and L^CLIP's clip range.
            alpha = 1.0 - (iteration - 1.0) / num_iterations
            optimizer.param_groups[0]["lr"].fill_(alpha * args.learning_rate if args.anneal_lr else args.learning_rate)
            epsilon = torch.tensor(alpha * args.clip_coef if args.anneal_clip else args.clip_coef, device=device)

            # ROLLOUT: run the policy pi_theta_old in N environments for T timesteps.
            with torch.inference_mode():
                for step in range(T):
                    global_step += N
                    buf.obs[step] = next_obs
                    action, buf.logprobs[step], _, buf.values[step] = agent.get_action_and_value(next_obs)
                    if fire is not None and lost_life.any():  # FIRE replaces the action; trained on
                        action = torch.where(torch.as_tensor(lost_life, device=device), fire, action)
                        _, buf.logprobs[step], _, buf.values[step] = agent.get_action_and_value(next_obs, action)
                    buf.actions[step] = action
                    next_obs, reward, term, trunc, infos = envs.step(action.cpu().numpy())
                    next_obs = torch.as_tensor(next_obs, device=device)
                    buf.terminations[step] = torch.as_tensor(term)
                    buf.truncations[step] = torch.as_tensor(trunc)
                    buf.rewards[step] = torch.as_tensor(np.sign(reward))  # atari detail 6: the reward's sign
                    game_ended = game_over(term, trunc, frame_numbers, infos["episode_frame_number"])
                    frame_numbers = infos["episode_frame_number"]
                    lost_life = term & ~game_ended  # atari detail 3: a termination within a game is a lost life
                    for i in np.flatnonzero(trunc):  # the true final observation of an episode cut by the time limit
                        final_obs = torch.as_tensor(infos["final_obs"][i][None], device=device)  # a batch of one
                        buf.final_values[step, i] = agent.get_value(final_obs)[0]
                    log.episodes(reward, game_ended, global_step)  # a game's score: the raw rewards over its lives
                    video.step(action[0], game_ended[0], frame_numbers[0], global_step)  # --capture-video, rank 0

                next_value = agent.get_value(next_obs)  # V(s_T), eq. (10)'s bootstrap

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
                    loss, stats = (compiled_loss or minibatch_loss)(agent, batch, mb_inds, epsilon, args)
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
            writer.add_scalar("charts/clip_coef", epsilon.item(), global_step)

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


class Agent(nn.Module):
    def __init__(self, num_actions):
        super().__init__()
        # Atari detail 8: the Nature-DQN CNN (§6.4 names the smaller one of [Mni+16]), shared by policy and value.
        conv1 = layer_init(nn.Conv2d(4, 32, 8, stride=4))
        conv2 = layer_init(nn.Conv2d(32, 64, 4, stride=2))
        conv3 = layer_init(nn.Conv2d(64, 64, 3, stride=1))
        fc = layer_init(nn.Linear(64 * 7 * 7, 512))
        self.network = nn.Sequential(conv1, nn.ReLU(), conv2, nn.ReLU(), conv3, nn.ReLU(), nn.Flatten(), fc, nn.ReLU())
        self.actor = layer_init(nn.Linear(512, num_actions), std=0.01)  # output gains 0.01 and 1 (core detail 2)
        self.critic = layer_init(nn.Linear(512, 1), std=1.0)

    def get_value(self, obs):
        return self.critic(self.network(obs / 255.0)).squeeze(-1)

    def get_action_and_value(self, obs, action=None):
        """An action sampled from pi(.|s) (or the given one), its log-prob, pi(.|s) itself, and V(s)."""
        hidden = self.network(obs / 255.0)  # atari detail 9: scale the uint8 frames to [0, 1] in the network
        probs = Categorical(logits=self.actor(hidden), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs, self.critic(hidden).squeeze(-1)


# ENVIRONMENT
def make_envs(args, num_envs=None, training=True):
    """ale-py's vector env: C++ emulators on their own threads, with atari details 1-5 and 7 (6 is in train())."""
    import ale_py

    game, repeat_action_probability = atari_game(args.env_id)
    num_envs = num_envs or args.num_envs
    return ale_py.AtariVectorEnv(
        game,
        num_envs,
        num_threads=min(num_envs, (os.cpu_count() or 1) // int(os.environ.get("LOCAL_WORLD_SIZE", 1)) or 1),
        max_num_frames_per_episode=args.max_episode_frames,  # a time limit: a truncation, whose value is bootstrapped
        repeat_action_probability=repeat_action_probability,  # sticky actions, for ALE/<Game>-v5 only
        noop_max=30,  # atari detail 1: up to 30 no-ops at the start of each game
        frameskip=4,  # atari detail 2: repeat each action for 4 frames,
        maxpool=True,  # and max-pool the last two
        life_loss_info=training,  # atari detail 3: a lost life ends an episode for learning; the game and score go on
        use_fire_reset=True,  # atari detail 4: press FIRE at the start of each game that needs it
        img_height=84,  # atari detail 5: 84x84 grayscale
        img_width=84,
        grayscale=True,
        stack_num=4,  # atari detail 7: the last 4 frames
        reward_clipping=False,  # atari detail 6 is in train(), where the raw score is logged too
        autoreset_mode="SameStep",  # as in ppo_continuous.py: the step that ends a game returns the next one's start
    )


def game_over(terminations, truncations, frame_numbers, new_frame_numbers):
    """Which envs ended a whole game: ALE's episode_frame_number restarts at a new game, goes on after a lost life."""
    return (terminations | truncations) & (new_frame_numbers < frame_numbers)


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
    """Play --eval-episodes whole games with the sampled policy of --eval-checkpoint (its argmax can stall)."""
    checkpoint, train_args = load_checkpoint(args.eval_checkpoint, args)
    device = pick_device(args.device)
    with contextlib.closing(make_envs(train_args, num_envs=1, training=False)) as envs:  # whole games: no life losses
        agent = Agent(envs.single_action_space.n)
        agent.to(device).load_state_dict(checkpoint["agent"])
        torch.manual_seed(args.seed)
        returns = []
        for game in range(args.eval_episodes):
            next_obs, infos = envs.reset(seed=args.seed + game)
            done = False
            game_return = 0.0
            actions = []
            while not done:
                with torch.inference_mode():
                    action, _, _, _ = agent.get_action_and_value(torch.as_tensor(next_obs, device=device))
                actions.append(int(action[0]))
                next_obs, reward, term, trunc, _ = envs.step(action.cpu().numpy())
                game_return += float(reward[0])
                done = bool(term[0] or trunc[0])
            returns.append(game_return)
            if args.capture_video:
                path = f"{train_args.run_dir}/videos-eval/eval-game-{game}.mp4"
                write_video(train_args.env_id, infos["episode_frame_number"][0], actions, path)
    summary = f"return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes"
    print(f"eval {train_args.env_id} step {checkpoint['global_step']:,}: {summary}")
    return returns


# ATARI GAMES: what an id means, and videos replayed from a game's reset and actions
def atari_game(env_id):
    """The ROM and sticky-action probability of an id: <Game>NoFrameskip-v4 repeats no action (the paper's games),
    ALE/<Game>-v5 the last one with probability 0.25. Else a ValueError, with the ids a loose name could mean."""
    import ale_py
    import gymnasium as gym  # importing ale_py registered its games

    ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)  # no banner on stderr
    if re.fullmatch(r"\w+NoFrameskip-v4|ALE/\w+-v5", env_id) and env_id in gym.registry:
        kwargs = gym.registry[env_id].kwargs
        return kwargs["game"], kwargs["repeat_action_probability"]
    names = {key[4:-3].lower(): key[4:-3] for key in gym.registry if key.startswith("ALE/") and key.endswith("-v5")}
    name = names.get(re.sub(r"(NoFrameskip|Deterministic)?(-v\d+)?$", "", env_id.split("/")[-1]).lower())
    could_mean = f"; did you mean {name}NoFrameskip-v4 (the paper's) or ALE/{name}-v5?" if name else ""
    games = "Atari games, with their discrete action space, <Game>NoFrameskip-v4 or ALE/<Game>-v5"
    raise ValueError(f"unknown env id {env_id!r}: this script plays {games}{could_mean}")


class GameVideo:
    """With --capture-video (`film`), env 0's games 0, 1, 8, 27, ...: write_video replays each from its reset and
    actions into the run's videos."""

    def __init__(self, env_id, run_dir, reset_frames, film):
        self.env_id = env_id
        self.video_dir = f"{run_dir}/videos" if film else None
        self.reset_frames = reset_frames
        self.actions = []
        self.games = 0

    def step(self, action, game_ended, frame_number, global_step):
        if self.video_dir is None:
            return
        self.actions.append(int(action))
        if game_ended:
            if self.games == round(self.games ** (1 / 3)) ** 3:
                path = f"{self.video_dir}/step-{global_step}-game-{self.games}.mp4"
                write_video(self.env_id, self.reset_frames, self.actions, path)
            self.games += 1
            self.actions = []
            self.reset_frames = frame_number


def write_video(env_id, reset_frames, actions, path):
    """Replay a game in a new emulator, every frame in colour (210x160) at 60 Hz, to an mp4. Without sticky actions the
    same reset (ale-py's: FIRE if the game has it, then no-ops, reset_frames in all) and actions play the same game."""
    import ale_py
    import imageio.v2 as imageio

    ale = ale_py.ALEInterface()
    ale.setFloat("repeat_action_probability", 0.0)
    ale.loadROM(ale_py.roms.get_rom_path(atari_game(env_id)[0]))
    ale.reset_game()  # as ale-py's reset does: some games (BeamRider) play differently without it
    action_set = ale.getMinimalActionSet()
    fire = [ale_py.Action.FIRE] * (ale_py.Action.FIRE in action_set)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    moves = (
        fire + [ale_py.Action.NOOP] * (reset_frames - len(fire)) + [action_set[a] for a in actions for _ in range(4)]
    )
    with imageio.get_writer(path, fps=60, macro_block_size=1) as video:
        for action in moves:
            ale.act(action)
            video.append_data(ale.getScreenRGB())


# A run ends early Stopped (Ctrl-C or SIGTERM, after a checkpoint) or Diverged (the last finite checkpoint kept).
class Stopped(Exception): ...


class Diverged(Exception): ...


def pick_device(name):
    return torch.device(("cuda" if torch.cuda.is_available() else "cpu") if name == "auto" else name)


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
WRITER = "ppo_atari.py"


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
POSITIVE = "total_timesteps max_episode_frames learning_rate num_envs num_steps minibatch_size update_epochs".split()
POSITIVE += "clip_coef max_grad_norm save_every eval_episodes torch_threads".split()
RANGES = {"gamma": (0, 1), "gae_lambda": (0, 1), "ent_coef": (0, math.inf), "vf_coef": (0, math.inf)}


def check_args(args):
    """Reject bad input before anything heavy loads, with a one-line reason (a ValueError)."""
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
    repeat_action_probability = atari_game(args.env_id)[1]  # a ValueError for an id that is not an Atari game's
    if args.resume or args.eval_checkpoint:  # a copy given another network refuses these weights, before any write
        with contextlib.closing(make_envs(args, num_envs=1, training=False)) as envs:
            check_network(Agent(envs.single_action_space.n), checkpoint["agent"], args.resume or args.eval_checkpoint)
    if args.capture_video and repeat_action_probability > 0:
        raise ValueError(f"--capture-video replays games, which the sticky actions of {args.env_id} make impossible")
    if args.capture_video and not all(map(importlib.util.find_spec, ["imageio", "imageio_ffmpeg"])):  # write_video's
        raise ValueError("--capture-video writes its videos with imageio and imageio-ffmpeg: pip install both")
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
