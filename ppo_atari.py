"""PPO-Clip for Atari, in one file, fast on a CPU.

Implements Proximal Policy Optimization as the paper ran it on Atari: Schulman et al. 2017,
"Proximal Policy Optimization Algorithms" (arXiv:1707.06347), §6.4 with the hyperparameters of its
Table 5: a CNN shared by the policy and the value function, the combined objective L^{CLIP+VF+S}
(eq. 9), N = 8 parallel actors collecting fixed-length segments of T = 128 steps (Algorithm 1),
GAE (eq. 11-12), and both the learning rate and the clip range annealed with alpha from 1 to 0.

Run it:

    python ppo_atari.py                                  # Breakout, 10M steps (40M frames)
    python ppo_atari.py --env-id PongNoFrameskip-v4 --total-timesteps 1000000
    python ppo_atari.py --help                           # every flag, with its default

On a 2-core CPU the agent makes a few hundred steps/s, so 1M steps take about an hour and the full
10M steps (the paper's 40M frames) most of a day; the README says what to expect.

Choices the paper leaves open follow "The 37 Implementation Details of PPO" (Huang et al. 2022).
Comments cite them as "core detail N" (their 13 core details) and "atari detail N" (their 9
Atari details); the README lists each one with the line that does it.
"""

from __future__ import annotations

import copy
import math
import os
import random
import re
import signal
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn


@dataclass
class Args:
    # Experiment
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment, part of the run directory's name"""
    seed: int = 1
    """seed of torch, numpy, random and the environments"""
    torch_threads: int = 2
    """torch CPU threads for the CNN (the emulators run on their own threads between network calls)"""
    run_dir: str | None = None
    """where TensorBoard logs and the checkpoint go (default: runs/{env_id}__{exp_name}__{seed}__{time})"""
    capture_video: bool = False
    """record what the agent sees: games 0, 1, 8, 27, ... of the first env in training, every game in evaluation"""

    # Algorithm: defaults are the paper's Atari settings (Table 5)
    env_id: str = "BreakoutNoFrameskip-v4"
    """an Atari game: a gymnasium ALE id (BreakoutNoFrameskip-v4, ALE/Breakout-v5) or a game name (Breakout)"""
    total_timesteps: int = 10_000_000
    """total agent steps over all envs (paper: 10M steps = 40M frames)"""
    learning_rate: float = 2.5e-4
    """Adam step size at the start, 2.5e-4 x alpha (paper: 2.5e-4)"""
    num_envs: int = 8
    """number of parallel actors N (paper: 8)"""
    num_steps: int = 128
    """steps per actor in each rollout, the horizon T (paper: 128)"""
    anneal_lr: bool = True
    """anneal the learning rate with alpha, linearly to 0 (paper §6.4; core detail 4)"""
    anneal_clip: bool = True
    """anneal the clip range with alpha, 0.1 x alpha (paper Table 5; CleanRL keeps it fixed)"""
    gamma: float = 0.99
    """discount factor gamma (paper: 0.99)"""
    gae_lambda: float = 0.95
    """GAE lambda (paper: 0.95)"""
    minibatch_size: int = 256
    """minibatch size (paper: 32 x 8 = 256); must divide num_envs * num_steps"""
    update_epochs: int = 3
    """epochs K over each rollout (paper: 3; CleanRL: 4)"""
    norm_adv: bool = True
    """normalize advantages per minibatch (core detail 7)"""
    clip_coef: float = 0.1
    """clip range epsilon of L^CLIP at the start (paper: 0.1 x alpha)"""
    clip_vloss: bool = True
    """clip the value loss around the old values (core detail 9)"""
    ent_coef: float = 0.01
    """entropy bonus coefficient c2 (paper: 0.01)"""
    vf_coef: float = 1.0
    """value loss coefficient c1 (paper: 1; CleanRL: 0.5)"""
    clip_grad_norm: bool = True
    """clip the global gradient norm (core detail 11)"""
    max_grad_norm: float = 0.5
    """the maximum global gradient norm, when clipping"""

    # Checkpoints and evaluation
    save_every: int = 50
    """write the checkpoint every this many iterations (it is also written at the end and on Ctrl-C)"""
    resume: str | None = None
    """continue the run saved in this checkpoint; its hyperparameters come from the checkpoint"""
    eval_checkpoint: str | None = None
    """evaluate the policy of this checkpoint instead of training"""
    eval_episodes: int = 10
    """number of games for --eval-checkpoint"""


# Flags that describe how to run, not what is trained: on --resume these come from the command line,
# everything else from the checkpoint.
RUNTIME_FIELDS = ("torch_threads", "capture_video", "save_every", "resume", "eval_checkpoint", "eval_episodes")


def args_from_checkpoint(checkpoint, args):
    """The Args of the run saved in `checkpoint`, with the RUNTIME_FIELDS of `args`."""
    return Args(**{**checkpoint["args"], **{k: getattr(args, k) for k in RUNTIME_FIELDS}})



# ALGORITHM


def compute_gae(rewards, values, next_values, terminations, truncations, gamma, gae_lambda):
    """Generalized advantage estimation, paper eq. (11)-(12), with truncation handled correctly.

    All inputs are [T, N] tensors. next_values[t] is V of the observation reached after step t; when
    the episode ended at step t, that is its final observation (not the next episode's first one).

        delta_t = r_t + gamma * (1 - term_t) * next_values_t - values_t
        A_t     = delta_t + gamma * lambda * (1 - done_t) * A_{t+1},   done_t = term_t or trunc_t

    A time-limit truncation is not a termination: the value of the final observation is still
    bootstrapped (Pardo et al. 2018), but the advantage does not flow across the episode boundary.
    returns = advantages + values is the TD(lambda) target of the value function (core detail 5).

    >>> one = torch.ones(3, 1)
    >>> adv, ret = compute_gae(one, 0 * one, 0 * one, torch.tensor([[0.], [0.], [1.]]), 0 * one, 0.5, 1.0)
    >>> adv.flatten().tolist()  # discounted reward-to-go with gamma = 0.5: 1 + .5 + .25, 1 + .5, 1
    [1.75, 1.5, 1.0]
    """
    terminations, truncations = terminations.float(), truncations.float()
    dones = torch.maximum(terminations, truncations)
    deltas = rewards + gamma * (1.0 - terminations) * next_values - values
    # The backward recursion is a Python loop over T rows. On numpy arrays each row costs about 1 us,
    # on small torch tensors about 5 us: the same arithmetic, 5x faster for T = 2048.
    deltas_np, decay = deltas.numpy(), (gamma * gae_lambda) * (1.0 - dones.numpy())
    advantages = np.zeros_like(deltas_np)
    lastgaelam = np.zeros_like(deltas_np[0])
    for t in reversed(range(deltas_np.shape[0])):
        lastgaelam = deltas_np[t] + decay[t] * lastgaelam
        advantages[t] = lastgaelam
    advantages = torch.from_numpy(advantages)
    return advantages, advantages + values


def clipped_surrogate_loss(ratio, advantages, clip_coef):
    """Minus L^CLIP, paper eq. (7): -E[min(r A, clip(r, 1 - eps, 1 + eps) A)] (core detail 8).

    >>> round(clipped_surrogate_loss(torch.tensor([1.5, 0.5]), torch.tensor([1.0, 1.0]), 0.2).item(), 6)  # min(1.5, 1.2), min(.5, .8)
    -0.85
    """
    pg_loss1 = -advantages * ratio
    pg_loss2 = -advantages * torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef)
    return torch.max(pg_loss1, pg_loss2).mean()


def value_loss(newvalue, oldvalue, returns, clip_coef, clip_vloss=True):
    """0.5 * squared error of V against the returns, optionally clipped (core detail 9).

    The clipped form comes from openai/baselines ppo2, not from the paper: the new value may move at
    most clip_coef away from the value at rollout time, and the larger of the two errors is used.
    Engstrom et al. (2020) found it does not help; keep it to compare with baselines and CleanRL,
    or pass --no-clip-vloss.
    """
    v_loss_unclipped = (newvalue - returns) ** 2
    if not clip_vloss:
        return 0.5 * v_loss_unclipped.mean()
    v_clipped = oldvalue + torch.clamp(newvalue - oldvalue, -clip_coef, clip_coef)
    v_loss_clipped = (v_clipped - returns) ** 2
    return 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()


# ENVIRONMENT


def game_name(env_id):
    """'BreakoutNoFrameskip-v4', 'ALE/Breakout-v5', 'Breakout' or 'breakout' -> the ROM name 'breakout'."""
    import ale_py
    import gymnasium as gym

    gym.register_envs(ale_py)
    for registered in (env_id, f"ALE/{env_id}-v5"):  # a registered ALE id knows its ROM's name
        try:
            return gym.spec(registered).kwargs["game"]  # UpNDown -> up_n_down, which no rule would guess
        except (gym.error.Error, KeyError):
            pass
    name = env_id.split("/")[-1]
    name = re.sub(r"(NoFrameskip)?(-v\d+)?$", "", name)
    name = re.sub(r"Deterministic$", "", name)
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", name).lower()


def make_envs(args, num_envs=None, training=True):
    """ale-py's native vector env: C++ emulators on their own threads, which do the whole
    preprocessing of atari details 1-7 themselves, about 2x faster here than gymnasium's
    SyncVectorEnv with one Python wrapper per preprocessing step per env."""
    import ale_py

    ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)  # no banner on stderr
    return ale_py.AtariVectorEnv(
        game_name(args.env_id),
        num_envs or args.num_envs,
        num_threads=min(num_envs or args.num_envs, os.cpu_count() or 1),
        # Sticky actions off: the paper's NoFrameskip-v4 envs are deterministic given the noops.
        # (ALE/...-v5 ids default to sticky actions; we use only their game name.)
        repeat_action_probability=0.0,
        # Atari detail 1: up to 30 no-ops at the start of each game.
        noop_max=30,
        # Atari detail 2: repeat each action for 4 frames and max-pool the last two.
        frameskip=4,
        maxpool=True,
        # Atari detail 3, episodic life, our way. ale-py's own `episodic_life=True` restarts the whole
        # game at every life lost, so the agent would never see its later lives and the logged score
        # would be one life's. `life_loss_info=True` instead marks a lost life as a termination (no
        # value bootstrapped across it, as EpisodicLifeEnv does) while the game goes on; the game
        # resets only when it is really over. Unlike EpisodicLifeEnv + FireResetEnv, nothing
        # presses FIRE after a lost life: the agent learns to, as it does in ALE v5 envs.
        life_loss_info=training,
        # Atari detail 4: press FIRE at the start of each game where the game needs it.
        use_fire_reset=True,
        # Atari detail 5: 84x84 grayscale. Atari detail 7: stack the last 4 frames, oldest first.
        img_height=84,
        img_width=84,
        grayscale=True,
        stack_num=4,
        # Atari detail 6 is done in train(), with np.sign, so that the raw game score stays
        # available for logging.
        reward_clipping=False,
        # Same-step autoreset, as in ppo_continuous.py: the step that ends a game returns the next
        # game's first observation, so every stored transition really happened.
        autoreset_mode="SameStep",
    )


def game_over(terminations, truncations, lives, new_lives):
    """Which envs finished a whole game this step, under life_loss_info (see make_envs).

    A lost life is a termination for learning, but the game goes on with fewer lives. A game is
    over when an env terminates without losing a life (the game ended; with same-step autoreset,
    new_lives is already the next game's count), or when it is truncated by the time limit.

    >>> game_over(np.array([True, True, True]), np.array([False] * 3), np.array([5, 1, 0]), np.array([4, 5, 0]))
    array([False,  True,  True])
    """
    return (terminations & ~(new_lives < lives)) | truncations


# AGENT


def layer_init(layer, std=math.sqrt(2), bias_const=0.0):
    # Core detail 2: orthogonal weights with gain sqrt(2) for hidden layers, constant 0 biases.
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, num_actions):
        super().__init__()
        # Atari detail 8: the Nature-DQN CNN (Mnih et al. 2015), shared by the policy and the value
        # function (paper §6.4; core detail 13).
        self.network = nn.Sequential(
            layer_init(nn.Conv2d(4, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
            layer_init(nn.Linear(64 * 7 * 7, 512)), nn.ReLU(),
        )  # fmt: skip
        # Core detail 2: output gains 0.01 for the policy (near-uniform at the start), 1 for the value.
        self.actor = layer_init(nn.Linear(512, num_actions), std=0.01)
        self.critic = layer_init(nn.Linear(512, 1), std=1.0)
        # Speed: channels-last (NHWC) is the layout oneDNN's CPU convolutions run fastest on. On
        # this project's 2-core CPU it makes the update 1.6-1.8x faster, close to the FLOP rate of
        # a plain matmul (benchmarks/atari_flops.py, benchmarks/results/atari_flops.md).
        self.to(memory_format=torch.channels_last)

    def forward(self, obs):
        """uint8 frames [B, 4, 84, 84] -> (logits [B, A], value [B])."""
        # Atari detail 9: scale to [0, 1] inside the network. The rollout keeps uint8 frames, a
        # quarter of the memory of float32 ones.
        hidden = self.network(obs.contiguous(memory_format=torch.channels_last).float() / 255.0)
        return self.actor(hidden), self.critic(hidden).squeeze(-1)


# CHECKPOINTS


def make_checkpoint(args, agent, optimizer, global_step, iteration):
    # Everything a resumed run needs, as plain tensors, numbers and strings, so that it loads with
    # torch.load(weights_only=True): a checkpoint is data and can never run code. deepcopy takes a
    # snapshot, so that Ctrl-C during an update still saves the last complete iteration.
    return {
        "format": "ppo-checkpoint-v1",
        "script": os.path.basename(__file__),
        "args": asdict(args),
        "agent": copy.deepcopy(agent.state_dict()),
        "optimizer": copy.deepcopy(optimizer.state_dict()),
        "global_step": global_step,
        "iteration": iteration,
        "torch_rng_state": torch.get_rng_state(),
    }


def save_checkpoint(checkpoint, path):
    # Write, then rename: os.replace is atomic, so a crash leaves the old file or the new one.
    tmp = f"{path}.tmp"
    torch.save(checkpoint, tmp)
    os.replace(tmp, path)


def load_checkpoint(path):
    """Load a checkpoint written by this script; raise ValueError with a one-line reason if it is not one."""
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"cannot read checkpoint {path!r}: it is corrupt or not a checkpoint ({type(e).__name__})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != "ppo-checkpoint-v1":
        raise ValueError(f"{path!r} is not a checkpoint written by these scripts")
    if checkpoint.get("script") != os.path.basename(__file__):
        raise ValueError(f"{path!r} was written by {checkpoint.get('script')}, not {os.path.basename(__file__)}")
    return checkpoint


def check_args(args):
    """Reject bad input before anything starts, with a one-line reason (raised as ValueError)."""
    for name in ("total_timesteps", "num_envs", "num_steps", "minibatch_size", "update_epochs", "save_every", "eval_episodes", "torch_threads"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.learning_rate <= 0 or args.clip_coef <= 0:
        raise ValueError("--learning-rate and --clip-coef must be positive")
    if not (0 <= args.gamma <= 1 and 0 <= args.gae_lambda <= 1):
        raise ValueError("--gamma and --gae-lambda must be in [0, 1]")
    if args.max_grad_norm <= 0 or args.vf_coef < 0 or args.ent_coef < 0:
        raise ValueError("--max-grad-norm must be positive, --vf-coef and --ent-coef at least 0")
    batch_size = args.num_envs * args.num_steps
    if batch_size % args.minibatch_size != 0:
        raise ValueError(f"--minibatch-size {args.minibatch_size} does not divide the batch of --num-envs x --num-steps = {batch_size}")
    if args.eval_checkpoint is None and args.resume is None and args.total_timesteps < batch_size:
        raise ValueError(f"--total-timesteps {args.total_timesteps} is less than one batch of {batch_size} steps")
    if args.resume is not None and args.eval_checkpoint is not None:
        raise ValueError("use either --resume or --eval-checkpoint, not both")
    for path in (args.resume, args.eval_checkpoint):
        if path is not None:
            args = args_from_checkpoint(load_checkpoint(path), args)
    from ale_py import roms

    if game_name(args.env_id) not in roms.get_all_rom_ids():
        import gymnasium as gym

        try:  # a gymnasium env that is not an Atari game: say what it is
            env = gym.make(args.env_id)
        except gym.error.Error:
            raise ValueError(f"unknown env id {args.env_id!r}: no Atari game {game_name(args.env_id)!r} ships with ale-py") from None
        space = env.action_space
        env.close()
        hint = "; use ppo_continuous.py for continuous control" if isinstance(space, gym.spaces.Box) else ""
        raise ValueError(f"{args.env_id} is not an Atari game (its action space is {space}); ppo_atari.py plays Atari games{hint}")


# TRAINING


def train(args):
    from torch.utils.tensorboard import SummaryWriter

    checkpoint = None
    if args.resume is not None:
        # The same run continues: its hyperparameters, weights, step and RNG come from the
        # checkpoint; only the flags in RUNTIME_FIELDS are taken from this command line.
        checkpoint = load_checkpoint(args.resume)
        args = args_from_checkpoint(checkpoint, args)
    batch_size = args.num_envs * args.num_steps
    num_iterations = args.total_timesteps // batch_size

    if checkpoint is not None:
        checkpoint_path = args.resume
        run_dir = os.path.dirname(os.path.abspath(checkpoint_path))  # the run goes on where its checkpoint is
    else:
        run_name = f"{args.env_id.replace('/', '-')}__{args.exp_name}__{args.seed}__{int(time.time())}"
        run_dir = args.run_dir or os.path.join("runs", run_name)
        checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    os.makedirs(run_dir, exist_ok=True)

    # Determinism: one seed for everything; on CPU the same seed gives the same run.
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)

    envs = make_envs(args)
    agent = Agent(envs.single_action_space.n)
    # Core detail 3: Adam with eps 1e-5 (PyTorch's default is 1e-8).
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)

    global_step, start_iteration = 0, 1
    if checkpoint is not None:
        agent.load_state_dict(checkpoint["agent"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        global_step, start_iteration = checkpoint["global_step"], checkpoint["iteration"] + 1
        torch.set_rng_state(checkpoint["torch_rng_state"])
        print(f"resuming {run_dir} at step {global_step:,} (iteration {checkpoint['iteration']}/{num_iterations})")
        if start_iteration > num_iterations:
            print("the run had already finished: nothing to do")
            return agent, run_dir

    # purge_step drops the events an interrupted run logged after its checkpoint's step, so the
    # TensorBoard curve continues from that step without a fold.
    writer = SummaryWriter(run_dir, purge_step=global_step + 1 if checkpoint is not None else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in asdict(args).items()))

    # Rollout storage. Frames stay uint8 (4 x 84 x 84 bytes per step) until the network.
    T, N = args.num_steps, args.num_envs
    obs = torch.zeros((T, N, 4, 84, 84), dtype=torch.uint8)
    actions = torch.zeros((T, N), dtype=torch.long)
    logprobs = torch.zeros((T, N))
    values = torch.zeros((T, N))
    rewards = np.zeros((T, N), dtype=np.float32)
    terminations = np.zeros((T, N), dtype=np.float32)
    truncations = np.zeros((T, N), dtype=np.float32)
    next_values = torch.zeros((T, N))

    # A resumed run starts new games (an emulator's state is not saved), seeded by the step so
    # that resuming is itself deterministic.
    next_obs, infos = envs.reset(seed=args.seed + global_step)
    lives = infos["lives"]
    episode_return = np.zeros(N)  # the raw game score, over all lives
    episode_length = np.zeros(N, dtype=np.int64)
    recent_returns = deque(maxlen=100)
    video_frames, games_of_env0 = [], 0

    snapshot = make_checkpoint(args, agent, optimizer, global_step, start_iteration - 1)
    start_time, start_step, last_print = time.time(), global_step, 0.0
    # The benchmark runner stops runs with SIGTERM: treat it like Ctrl-C, which saves the checkpoint.
    previous_sigterm = signal.signal(signal.SIGTERM, lambda signum, frame: (_ for _ in ()).throw(KeyboardInterrupt()))

    try:
        for iteration in range(start_iteration, num_iterations + 1):
            # alpha goes linearly from 1 to 0 over training (paper §6.4, Table 5). Core detail 4:
            # it anneals the learning rate; the paper also anneals the clip range with it, which
            # CleanRL does not (--no-anneal-clip gives CleanRL's fixed 0.1).
            alpha = 1.0 - (iteration - 1.0) / num_iterations
            optimizer.param_groups[0]["lr"] = alpha * args.learning_rate if args.anneal_lr else args.learning_rate
            clip_coef = alpha * args.clip_coef if args.anneal_clip else args.clip_coef

            # ROLLOUT
            next_values.zero_()
            with torch.inference_mode():
                for step in range(T):
                    global_step += N
                    obs[step] = torch.from_numpy(next_obs)
                    logits, value = agent(obs[step])
                    # Sample from the categorical policy with the Gumbel-max trick: argmax(logits + Gumbel
                    # noise) is an exact sample, without building a Categorical object per step.
                    action = torch.argmax(logits - torch.log(-torch.log(torch.rand_like(logits))), dim=-1)
                    actions[step], values[step] = action, value
                    logprobs[step] = torch.log_softmax(logits, -1).gather(-1, action[:, None]).squeeze(-1)
                    next_obs, reward, term, trunc, infos = envs.step(action.numpy())

                    # Atari detail 6: train on the sign of the reward; log the raw score.
                    rewards[step] = np.sign(reward)
                    terminations[step], truncations[step] = term, trunc
                    episode_return += reward
                    episode_length += 1
                    finished = game_over(term, trunc, lives, infos["lives"])
                    lives = infos["lives"]
                    if trunc.any():
                        # Bootstrap from the true final observation of a game cut by the time limit.
                        final_obs = torch.from_numpy(np.stack(infos["final_obs"][trunc]))
                        next_values[step, torch.from_numpy(trunc)] = agent(final_obs)[1]

                    if args.capture_video and games_of_env0 == round(games_of_env0 ** (1 / 3)) ** 3:
                        video_frames.append(obs[step, 0, -1].numpy().copy())  # a copy: obs is reused
                    for i in np.flatnonzero(finished):
                        recent_returns.append(episode_return[i])
                        writer.add_scalar("charts/episodic_return", episode_return[i], global_step)
                        writer.add_scalar("charts/episodic_length", episode_length[i], global_step)
                        episode_return[i], episode_length[i] = 0.0, 0
                        if i == 0:
                            if video_frames:
                                write_video(video_frames, os.path.join(run_dir, "videos", f"step-{global_step}-game-{games_of_env0}.mp4"))
                            video_frames, games_of_env0 = [], games_of_env0 + 1

                # ADVANTAGES: next_values[t] = V(s_{t+1}), the next row of values, V(next_obs)
                # after the last step, and V(final observation) where a game was truncated (set
                # above). Where a life was lost, compute_gae multiplies it by 0 (no bootstrap).
                done = torch.from_numpy(np.maximum(terminations, truncations)).bool()
                next_values[:-1] = torch.where(done[:-1], next_values[:-1], values[1:])
                next_values[-1] = torch.where(done[-1], next_values[-1], agent(torch.from_numpy(next_obs))[1])
            advantages, returns = compute_gae(
                torch.from_numpy(rewards), values, next_values, torch.from_numpy(terminations), torch.from_numpy(truncations),
                args.gamma, args.gae_lambda,
            )  # fmt: skip

            # UPDATE
            b_obs = obs.reshape(-1, 4, 84, 84)
            b_actions = actions.reshape(-1)
            b_logprobs = logprobs.reshape(-1)
            b_advantages = advantages.reshape(-1)
            b_returns = returns.reshape(-1)
            b_values = values.reshape(-1)

            stats = []
            for epoch in range(args.update_epochs):
                # Core detail 6: shuffle the whole batch each epoch and split it into minibatches.
                b_inds = torch.randperm(batch_size)
                for start in range(0, batch_size, args.minibatch_size):
                    mb_inds = b_inds[start : start + args.minibatch_size]
                    logits, newvalue = agent(b_obs[mb_inds])
                    logp_all = torch.log_softmax(logits, -1)
                    newlogprob = logp_all.gather(-1, b_actions[mb_inds, None]).squeeze(-1)
                    entropy = -(logp_all.exp() * logp_all).sum(-1).mean()
                    logratio = newlogprob - b_logprobs[mb_inds]
                    ratio = logratio.exp()  # r_t(theta), paper eq. (6)

                    mb_advantages = b_advantages[mb_inds]
                    if args.norm_adv:
                        # Core detail 7: normalize the advantages of each minibatch.
                        mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)

                    pg_loss = clipped_surrogate_loss(ratio, mb_advantages, clip_coef)
                    v_loss = value_loss(newvalue, b_values[mb_inds], b_returns[mb_inds], clip_coef, args.clip_vloss)
                    # Core detail 10, paper eq. (9): L^{CLIP+VF+S} with c1 = 1 and c2 = 0.01, signs
                    # flipped to minimize.
                    loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss

                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if args.clip_grad_norm:
                        # Core detail 11: clip the global norm of all gradients together.
                        nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm, foreach=True)
                    optimizer.step()

                    # Core detail 12: debug statistics. approx_kl is the (r - 1) - log r
                    # estimator of KL[old, new] (http://joschu.net/blog/kl-approx.html).
                    with torch.no_grad():
                        stats.append(torch.stack([
                            pg_loss, v_loss, entropy, (-logratio).mean(), ((ratio - 1) - logratio).mean(),
                            ((ratio - 1.0).abs() > clip_coef).float().mean(),
                        ]))  # fmt: skip

            # LOGGING: the mean over every minibatch of the update, not the last minibatch's value.
            pg_mean, v_mean, ent_mean, old_kl_mean, kl_mean, clipfrac_mean = torch.stack(stats).mean(0).tolist()
            var_y = b_returns.var()
            explained_var = float("nan") if var_y == 0 else (1 - (b_returns - b_values).var() / var_y).item()
            sps = int((global_step - start_step) / (time.time() - start_time))
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/clip_coef", clip_coef, global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            writer.add_scalar("losses/policy_loss", pg_mean, global_step)
            writer.add_scalar("losses/value_loss", v_mean, global_step)
            writer.add_scalar("losses/entropy", ent_mean, global_step)
            writer.add_scalar("losses/old_approx_kl", old_kl_mean, global_step)
            writer.add_scalar("losses/approx_kl", kl_mean, global_step)
            writer.add_scalar("losses/clipfrac", clipfrac_mean, global_step)
            writer.add_scalar("losses/explained_variance", explained_var, global_step)

            # CHECKPOINT
            snapshot = make_checkpoint(args, agent, optimizer, global_step, iteration)
            if iteration % args.save_every == 0 or iteration == num_iterations:
                writer.flush()  # the curve on disk reaches at least the checkpoint's step
                save_checkpoint(snapshot, checkpoint_path)

            # PROGRESS: one line, rewritten in place on a terminal, printed every 30 s in a log.
            now = time.time()
            if sys.stdout.isatty() or now - last_print > 30 or iteration == num_iterations:
                last_print = now
                eta = (args.total_timesteps - global_step) / max(sps, 1)
                recent = f"{np.mean(recent_returns):9.1f}" if recent_returns else "      n/a"
                line = (f"step {global_step:>9,}/{num_iterations * batch_size:,} ({global_step / (num_iterations * batch_size):4.0%})"
                        f" | SPS {sps:5d} | return (last {len(recent_returns)}) {recent} | ETA {eta / 60:5.1f} min")  # fmt: skip
                end = "\n" if not sys.stdout.isatty() or iteration == num_iterations else ""
                print(("\r" if sys.stdout.isatty() else "") + line, end=end, flush=True)
        if video_frames:  # the game being recorded has not ended: keep what there is
            write_video(video_frames, os.path.join(run_dir, "videos", f"step-{global_step}-game-{games_of_env0}-unfinished.mp4"))
    except KeyboardInterrupt:
        writer.flush()
        save_checkpoint(snapshot, checkpoint_path)
        print(f"\ninterrupted: saved step {snapshot['global_step']:,} to {checkpoint_path}; continue with --resume {checkpoint_path}")
        sys.exit(130)
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        envs.close()
        writer.close()
    print(f"saved {checkpoint_path}")
    return agent, run_dir


# EVALUATION


def write_video(frames, path, scale=4):
    """Grayscale 84x84 frames, what the agent sees, -> an mp4 scaled up 4x."""
    import imageio.v3 as iio

    os.makedirs(os.path.dirname(path), exist_ok=True)
    video = np.repeat(np.repeat(np.stack(frames), scale, axis=1), scale, axis=2)
    iio.imwrite(path, np.repeat(video[..., None], 3, axis=-1), fps=15)


def evaluate(args):
    """Play --eval-episodes whole games with the policy of --eval-checkpoint; report the raw score.

    The policy is sampled, not its argmax: a deterministic Atari policy can wait forever (in
    Breakout, by never pressing FIRE), and the training score is that of the sampled policy.
    """
    checkpoint = load_checkpoint(args.eval_checkpoint)
    train_args = args_from_checkpoint(checkpoint, args)
    torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    envs = make_envs(train_args, num_envs=1, training=False)  # whole games: no life-loss terminations
    agent = Agent(envs.single_action_space.n)
    agent.load_state_dict(checkpoint["agent"])
    video_dir = os.path.join(os.path.dirname(os.path.abspath(args.eval_checkpoint)), "videos-eval")

    returns = []
    with torch.inference_mode():
        for game in range(args.eval_episodes):
            next_obs, _ = envs.reset(seed=args.seed + game)
            done, game_return, frames = False, 0.0, []
            while not done:
                if args.capture_video:
                    frames.append(next_obs[0, -1].copy())
                logits, _ = agent(torch.from_numpy(next_obs))
                action = torch.argmax(logits - torch.log(-torch.log(torch.rand_like(logits))), dim=-1)
                next_obs, reward, term, trunc, _ = envs.step(action.numpy())
                game_return += float(reward[0])
                done = bool(term[0] or trunc[0])
            returns.append(game_return)
            if args.capture_video:
                write_video(frames, os.path.join(video_dir, f"eval-game-{game}.mp4"))
    envs.close()
    print(f"eval {train_args.env_id} step {checkpoint['global_step']:,}: return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes")
    return returns


def main():
    import tyro

    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        # One line, no traceback, before anything starts.
        print(f"{os.path.basename(__file__)}: error: {e}", file=sys.stderr)
        sys.exit(2)
    if args.eval_checkpoint is not None:
        evaluate(args)
    else:
        train(args)


if __name__ == "__main__":
    main()
