"""PPO with the adaptive KL penalty for continuous control on MuJoCo, in one file.

Implements the second algorithm of Schulman et al. 2017, "Proximal Policy Optimization Algorithms"
(arXiv:1707.06347): §4, the KL-penalized objective (eq. 8, L^KLPEN) with the adaptive penalty
coefficient beta, inside the same Algorithm 1 (§5, with GAE, eq. 11-12) and MuJoCo setup (§6.1,
Table 3) as ppo_continuous.py. It is that script with only the objective changed:
`diff ppo_continuous.py ppo_kl_penalty.py` shows exactly what the KL penalty changes.

With its flags it runs every row of the paper's Table 1 that is not clipping:

    python ppo_kl_penalty.py                                     # adaptive KL, d_targ = 0.01
    python ppo_kl_penalty.py --kl-target 0.003                   # adaptive KL, d_targ = 0.003
    python ppo_kl_penalty.py --init-beta 3 --no-adaptive-beta    # fixed KL, beta = 3
    python ppo_kl_penalty.py --init-beta 0 --no-adaptive-beta    # no clipping or penalty

On a 2-core laptop CPU the default run (Hopper-v5, 1M steps) takes about 10-15 minutes.

Choices the paper leaves open follow "The 37 Implementation Details of PPO" (Huang et al. 2022).
Comments cite them as "core detail N" (their 13 core details) and "continuous detail N" (their 9
details for continuous actions); the README lists each one with the line that does it.
"""

from __future__ import annotations

import copy
import math
import os
import random
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
    torch_threads: int = 1
    """torch CPU threads; 1 is fastest for 64x64 MLPs, where intra-op threads cost more than they save"""
    run_dir: str | None = None
    """where TensorBoard logs and the checkpoint go (default: runs/{env_id}__{exp_name}__{seed}__{time})"""
    capture_video: bool = False
    """record videos of the first environment (during training) or of every evaluation episode"""

    # Algorithm: defaults are the paper's MuJoCo settings (Table 3)
    env_id: str = "Hopper-v5"
    """the id of a gymnasium environment with a Box action space"""
    total_timesteps: int = 1_000_000
    """total environment steps to train for (paper: 1M)"""
    learning_rate: float = 3e-4
    """Adam step size (paper: 3e-4)"""
    num_envs: int = 1
    """number of parallel environments (paper: 1 actor for MuJoCo)"""
    num_steps: int = 2048
    """steps per environment in each rollout, the horizon T (paper: 2048)"""
    anneal_lr: bool = True
    """anneal the learning rate linearly to 0 (core detail 4)"""
    gamma: float = 0.99
    """discount factor gamma (paper: 0.99)"""
    gae_lambda: float = 0.95
    """GAE lambda (paper: 0.95)"""
    minibatch_size: int = 64
    """minibatch size (paper: 64); must divide num_envs * num_steps"""
    update_epochs: int = 10
    """epochs K over each rollout (paper: 10)"""
    norm_adv: bool = True
    """normalize advantages per minibatch (core detail 7)"""
    clip_coef: float = 0.2
    """clip range of the value loss (core detail 9); the policy objective is not clipped in this script"""
    kl_target: float = 0.01
    """d_targ, the KL per update that the adaptive rule aims for (paper §4; Table 1: 0.003, 0.01, 0.03)"""
    init_beta: float = 1.0
    """the initial KL penalty coefficient beta (paper §6.1: 1)"""
    adaptive_beta: bool = True
    """adapt beta after each update (paper §4); --no-adaptive-beta keeps it fixed, as in Table 1's fixed-KL rows"""
    clip_vloss: bool = True
    """clip the value loss around the old values (core detail 9)"""
    ent_coef: float = 0.0
    """entropy bonus coefficient c2 (paper, MuJoCo: no entropy bonus)"""
    vf_coef: float = 0.5
    """value loss coefficient c1 (core detail 10)"""
    clip_grad_norm: bool = True
    """clip the global gradient norm (core detail 11)"""
    max_grad_norm: float = 0.5
    """the maximum global gradient norm, when clipping"""
    norm_obs: bool = True
    """normalize observations with running statistics (continuous details 6-7)"""
    norm_reward: bool = True
    """scale rewards by the running std of the discounted return (continuous details 8-9)"""

    # Checkpoints and evaluation
    save_every: int = 10
    """write the checkpoint every this many iterations (it is also written at the end and on Ctrl-C)"""
    resume: str | None = None
    """continue the run saved in this checkpoint; its hyperparameters come from the checkpoint"""
    eval_checkpoint: str | None = None
    """evaluate the deterministic policy of this checkpoint instead of training"""
    eval_episodes: int = 10
    """number of episodes for --eval-checkpoint"""


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


def gaussian_kl(mean_old, logstd_old, mean_new, logstd_new):
    """KL[old || new] between diagonal Gaussians, per sample, summed over the last dimension.

    Exact, in closed form: for each action dimension,
        log(s_new / s_old) + (s_old^2 + (m_old - m_new)^2) / (2 s_new^2) - 1/2.
    This is the KL[pi_old(.|s), pi_theta(.|s)] of paper eq. (8), not a sample estimate.

    >>> gaussian_kl(torch.zeros(1), torch.zeros(1), torch.ones(1), torch.zeros(1)).item()  # N(0,1) -> N(1,1): (0-1)^2 / 2
    0.5
    """
    var_ratio = torch.exp(2.0 * (logstd_old - logstd_new))
    mean_term = (mean_old - mean_new).pow(2) * torch.exp(-2.0 * logstd_new)
    return (logstd_new - logstd_old + 0.5 * (var_ratio + mean_term) - 0.5).sum(-1)


def kl_penalty_loss(ratio, advantages, kl, beta):
    """Minus L^KLPEN, paper eq. (8): -E[r A - beta KL[pi_old, pi_theta]].

    With beta = 0 this is minus the unclipped objective L^CPI (eq. 6), Table 1's "no clipping or
    penalty" row.
    """
    return -(ratio * advantages - beta * kl).mean()


def adapt_beta(beta, kl, kl_target):
    """The adaptive penalty coefficient of paper §4, applied after each policy update.

    With d = E[KL] measured over the whole batch: if d < d_targ / 1.5, beta <- beta / 2; if
    d > d_targ x 1.5, beta <- beta x 2; otherwise beta is kept. The paper chose 1.5 and 2
    heuristically and reports that the algorithm is not very sensitive to them.

    >>> adapt_beta(1.0, 0.001, 0.01), adapt_beta(1.0, 0.01, 0.01), adapt_beta(1.0, 0.1, 0.01)
    (0.5, 1.0, 2.0)
    """
    if kl < kl_target / 1.5:
        return beta / 2.0
    if kl > kl_target * 1.5:
        return beta * 2.0
    return beta


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


def gaussian_log_prob(action, mean, logstd):
    """log N(action; mean, exp(logstd)), summed over action dimensions (continuous details 1, 3).

    Written out instead of torch.distributions.Normal: it is the same formula without the argument
    validation and object construction, which cost more than the arithmetic at these sizes.
    """
    z = (action - mean) * torch.exp(-logstd)
    return (-0.5 * z.pow(2) - logstd).sum(-1) - 0.5 * math.log(2 * math.pi) * action.shape[-1]


class RunningMeanStd(nn.Module):
    """Running mean and variance of a stream of batches (Chan et al.'s parallel algorithm).

    The statistics belong to the agent, not to an env wrapper: they travel in its state_dict, and so
    in every checkpoint, and the saved policy sees the same inputs at evaluation as in training.
    They are kept as numpy arrays because update() runs on every env step, on numpy observations
    and rewards, where numpy takes about 1 us per operation and torch 3-5 us.
    """

    def __init__(self, shape=(), epsilon=1e-4):
        super().__init__()
        self.mean, self.var, self.count = np.zeros(shape), np.ones(shape), epsilon

    def update(self, x):
        """Add a batch x of shape [B, *shape] to the statistics."""
        batch_mean, batch_count = x.mean(0), x.shape[0]
        batch_var = np.square(x - batch_mean).mean(0)
        delta = batch_mean - self.mean
        total = self.count + batch_count
        self.var = (self.var * self.count + batch_var * batch_count + np.square(delta) * self.count * batch_count / total) / total
        self.mean = self.mean + delta * batch_count / total
        self.count = total

    # nn.Module saves and loads these with the rest of the agent's state_dict.
    def get_extra_state(self):
        return {"mean": torch.tensor(self.mean), "var": torch.tensor(self.var), "count": self.count}

    def set_extra_state(self, state):
        self.mean, self.var, self.count = state["mean"].numpy(), state["var"].numpy(), float(state["count"])


# ENVIRONMENT


def make_env(env_id, idx, capture_video, video_dir):
    def thunk():
        import gymnasium as gym

        if capture_video and idx == 0:
            env = gym.make(env_id, render_mode="rgb_array")
            env = gym.wrappers.RecordVideo(env, video_dir)
        else:
            env = gym.make(env_id)
        # No other wrappers. Action clipping (continuous detail 5), observation normalization and
        # reward scaling (continuous details 6-9) and episode statistics are done in train(), on the
        # whole batch of envs at once, instead of in one Python wrapper per env per step.
        return env

    return thunk


def make_envs(args, video_dir=None):
    import gymnasium as gym

    # Core detail 1: a vector of envs stepped together. Gymnasium 1.x vector envs default to
    # NEXT_STEP autoreset: the step after an episode ends returns the reset observation with a
    # reward of 0 and ignores the action, so code written for gym 0.2x stores a transition that never
    # happened. We choose SAME_STEP, the gym 0.2x behaviour: the step that ends an episode already
    # returns the next episode's first observation, and the true final observation comes in
    # infos["final_obs"], which is what we need to bootstrap a truncated episode. Every step of the
    # rollout is then a real transition, and the batch keeps exactly num_steps of them per env.
    return gym.vector.SyncVectorEnv(
        [make_env(args.env_id, i, args.capture_video, video_dir) for i in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )


# AGENT


def layer_init(layer, std=math.sqrt(2), bias_const=0.0):
    # Core detail 2: orthogonal weights with gain sqrt(2) for hidden layers, constant 0 biases.
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, obs_dim, act_dim, norm_obs=True):
        super().__init__()
        # Core detail 13 / continuous detail 4: separate 64x64 tanh networks, no shared parameters
        # (paper §6.1). Output gains follow core detail 2: 1 for the value, 0.01 for the policy mean,
        # so that the initial policy is close to N(0, 1) whatever the observation.
        self.critic = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 1), std=1.0),
        )  # fmt: skip
        self.actor_mean = nn.Sequential(
            layer_init(nn.Linear(obs_dim, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, 64)), nn.Tanh(),
            layer_init(nn.Linear(64, act_dim), std=0.01),
        )  # fmt: skip
        # Continuous detail 2: a state-independent log std, a learned vector starting at 0 (std 1).
        self.actor_logstd = nn.Parameter(torch.zeros(act_dim))
        self.norm_obs = norm_obs
        self.obs_rms = RunningMeanStd((obs_dim,))  # continuous detail 6
        self.return_rms = RunningMeanStd(())  # continuous detail 8

    def normalize_obs(self, raw_obs):
        """Raw numpy observations -> float32 numpy network inputs, with the current statistics."""
        if not self.norm_obs:
            return raw_obs.astype(np.float32)
        # Continuous detail 7: clip the normalized observation to [-10, 10].
        return np.clip((raw_obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + 1e-8), -10.0, 10.0).astype(np.float32)

    def get_value(self, obs):
        return self.critic(obs).squeeze(-1)


# CHECKPOINTS


def make_checkpoint(args, agent, optimizer, global_step, iteration, beta):
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
        "beta": beta,  # the adapted KL coefficient is part of the run's state
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
    import gymnasium as gym

    for name in ("total_timesteps", "num_envs", "num_steps", "minibatch_size", "update_epochs", "save_every", "eval_episodes", "torch_threads"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name.replace('_', '-')} must be positive, got {getattr(args, name)}")
    if args.learning_rate <= 0 or args.clip_coef <= 0 or args.kl_target <= 0:
        raise ValueError("--learning-rate, --clip-coef and --kl-target must be positive")
    if args.init_beta < 0:
        raise ValueError(f"--init-beta must be at least 0, got {args.init_beta}")
    if args.init_beta == 0 and args.adaptive_beta:
        raise ValueError("--init-beta 0 never adapts (halving or doubling 0 leaves 0); add --no-adaptive-beta for the unpenalized objective")
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
    try:  # register the Atari ids too, so that one gets the discrete-action message below
        import ale_py

        gym.register_envs(ale_py)
        ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)  # no banner on stderr
    except ImportError:
        pass
    try:
        env = gym.make(args.env_id)
    except gym.error.Error as e:
        raise ValueError(f"unknown env id {args.env_id!r}: {e}") from None
    action_space, observation_space = env.action_space, env.observation_space
    env.close()
    if not isinstance(action_space, gym.spaces.Box):
        raise ValueError(f"{args.env_id} has a {action_space} action space; {os.path.basename(__file__)} needs a Box action space. Use ppo_atari.py for discrete actions")
    if not isinstance(observation_space, gym.spaces.Box) or len(observation_space.shape) != 1:
        raise ValueError(f"{args.env_id} has a {observation_space} observation space; {os.path.basename(__file__)} needs a flat Box")


# TRAINING


def train(args):
    import gymnasium as gym
    from torch.utils.tensorboard import SummaryWriter

    checkpoint = None
    if args.resume is not None:
        # The same run continues: its hyperparameters, weights, statistics, step and RNG come from
        # the checkpoint; only the flags in RUNTIME_FIELDS are taken from this command line.
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
    if args.capture_video:
        os.environ.setdefault("MUJOCO_GL", "egl")  # render headless, without a display

    # Determinism: one seed for everything; on CPU the same seed gives the same run.
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)

    # Videos of a resumed run go to a folder of their own, so that they overwrite none of the earlier ones.
    first_step = checkpoint["global_step"] if checkpoint is not None else 0
    envs = make_envs(args, video_dir=os.path.join(run_dir, "videos", f"from-step-{first_step}"))
    obs_dim, act_dim = envs.single_observation_space.shape[0], envs.single_action_space.shape[0]
    action_low, action_high = envs.single_action_space.low, envs.single_action_space.high

    agent = Agent(obs_dim, act_dim, norm_obs=args.norm_obs)
    # Core detail 3: Adam with eps 1e-5 (PyTorch's default is 1e-8). fused=True runs the whole
    # parameter update as one kernel instead of a dozen small ops per parameter tensor.
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5, fused=True)

    global_step, start_iteration, beta = 0, 1, args.init_beta
    if checkpoint is not None:
        agent.load_state_dict(checkpoint["agent"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        global_step, start_iteration, beta = checkpoint["global_step"], checkpoint["iteration"] + 1, checkpoint["beta"]
        torch.set_rng_state(checkpoint["torch_rng_state"])
        print(f"resuming {run_dir} at step {global_step:,} (iteration {checkpoint['iteration']}/{num_iterations})")
        if start_iteration > num_iterations:
            print("the run had already finished: nothing to do")
            return agent, run_dir

    # purge_step drops the events an interrupted run logged after its checkpoint's step, so the
    # TensorBoard curve continues from that step without a fold.
    writer = SummaryWriter(run_dir, purge_step=global_step + 1 if checkpoint is not None else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in asdict(args).items()))

    # Rollout storage. The buffers are numpy arrays: writing a row costs well under 1 us, against
    # about 3 us for a torch tensor, and torch.from_numpy turns them into tensors without a copy
    # once per rollout. Observations are stored normalized: they are the networks' inputs.
    T, N = args.num_steps, args.num_envs
    obs = np.zeros((T, N, obs_dim), dtype=np.float32)
    actions = np.zeros((T, N, act_dim), dtype=np.float32)
    rewards = np.zeros((T, N), dtype=np.float32)
    terminations = np.zeros((T, N), dtype=np.float32)
    truncations = np.zeros((T, N), dtype=np.float32)
    final_obs = np.zeros((T, N, obs_dim), dtype=np.float32)  # filled where an episode was truncated

    def observe(raw_obs):
        """Raw env observations -> normalized float32 inputs, updating the running statistics."""
        if args.norm_obs:
            agent.obs_rms.update(raw_obs)  # continuous detail 6
        return agent.normalize_obs(raw_obs)

    # A resumed run starts fresh episodes (a MuJoCo state mid-episode is not saved), seeded by
    # the step so that resuming is itself deterministic.
    next_obs_raw, _ = envs.reset(seed=args.seed + global_step)
    next_obs = observe(next_obs_raw)
    discounted_return = np.zeros(N)  # for reward scaling
    episode_return = np.zeros(N)
    episode_length = np.zeros(N, dtype=np.int64)
    recent_returns = deque(maxlen=100)

    snapshot = make_checkpoint(args, agent, optimizer, global_step, start_iteration - 1, beta)
    start_time, start_step, last_print = time.time(), global_step, 0.0
    # The benchmark runner stops runs with SIGTERM: treat it like Ctrl-C, which saves the checkpoint.
    previous_sigterm = signal.signal(signal.SIGTERM, lambda signum, frame: (_ for _ in ()).throw(KeyboardInterrupt()))

    try:
        for iteration in range(start_iteration, num_iterations + 1):
            # Core detail 4: anneal the learning rate linearly from its initial value to 0. The
            # paper's Table 3 gives a fixed 3e-4, but the code that produced its MuJoCo results
            # (openai/baselines ppo1, run_mujoco.py) anneals it with schedule="linear". That code
            # also annealed the clip range with the same factor; we keep epsilon fixed, as the
            # paper's text and Table 1 state it.
            if args.anneal_lr:
                frac = 1.0 - (iteration - 1.0) / num_iterations
                optimizer.param_groups[0]["lr"] = frac * args.learning_rate

            # ROLLOUT
            # Per step we run only what must be sequential: normalize, the policy mean, a Gaussian
            # sample, and the env. The value V(s_t) and log pi(a_t|s_t) do not change during the
            # rollout, so they are computed afterwards for the whole batch in one call each, at a
            # small fraction of the cost of 2048 single-row calls.
            action_std = torch.exp(agent.actor_logstd.detach())
            with torch.inference_mode():
                for step in range(T):
                    global_step += N
                    obs[step] = next_obs
                    action_mean = agent.actor_mean(torch.from_numpy(next_obs))
                    action = (action_mean + action_std * torch.randn(N, act_dim)).numpy()
                    actions[step] = action  # the unclipped sample: its log-prob is what the ratio uses
                    # Continuous detail 5: clip the action to the valid range only for the env.
                    next_obs_raw, reward, term, trunc, infos = envs.step(np.clip(action, action_low, action_high))
                    next_obs = observe(next_obs_raw)
                    done = term | trunc

                    rewards[step] = reward
                    if args.norm_reward:
                        # Continuous details 8-9: divide the reward by the running std of the
                        # discounted return (not the reward's own std, and without subtracting a
                        # mean), then clip it to [-10, 10].
                        discounted_return = discounted_return * args.gamma + reward
                        agent.return_rms.update(discounted_return)
                        rewards[step] = np.clip(reward / np.sqrt(agent.return_rms.var + 1e-8), -10.0, 10.0)
                        discounted_return[done] = 0.0
                    terminations[step] = term
                    truncations[step] = trunc

                    episode_return += reward  # the raw reward: logged returns are the env's own
                    episode_length += 1
                    for i in np.flatnonzero(done):
                        if trunc[i]:
                            # SAME_STEP autoreset: next_obs_raw[i] already starts a new episode. Keep
                            # the true final observation, normalized but not added to the statistics,
                            # to bootstrap from it.
                            final_obs[step, i] = agent.normalize_obs(infos["final_obs"][i])
                        recent_returns.append(episode_return[i])
                        writer.add_scalar("charts/episodic_return", episode_return[i], global_step)
                        writer.add_scalar("charts/episodic_length", episode_length[i], global_step)
                        episode_return[i], episode_length[i] = 0.0, 0

            # ADVANTAGES
            t_obs, t_actions, t_final_obs = torch.from_numpy(obs), torch.from_numpy(actions), torch.from_numpy(final_obs)
            t_rewards, t_terminations, t_truncations = torch.from_numpy(rewards), torch.from_numpy(terminations), torch.from_numpy(truncations)
            with torch.no_grad():
                # pi_old, kept for the exact KL of the penalty: its means and its log std.
                old_means, old_logstd = agent.actor_mean(t_obs), agent.actor_logstd.clone()
                logprobs = gaussian_log_prob(t_actions, old_means, old_logstd)
                values = agent.get_value(t_obs)
                # next_values[t] = V(s_{t+1}): the next row of values, V(next_obs) after the last
                # step, and V(final observation) where an episode was truncated. Where it
                # terminated, compute_gae multiplies it by 0 (no bootstrap).
                next_values = torch.cat([values[1:], agent.get_value(torch.from_numpy(next_obs))[None]])
                trunc_mask = t_truncations.bool()
                if trunc_mask.any():
                    next_values[trunc_mask] = agent.get_value(t_final_obs[trunc_mask])
            advantages, returns = compute_gae(t_rewards, values, next_values, t_terminations, t_truncations, args.gamma, args.gae_lambda)

            # UPDATE
            b_obs = t_obs.reshape(-1, obs_dim)
            b_actions = t_actions.reshape(-1, act_dim)
            b_logprobs = logprobs.reshape(-1)
            b_advantages = advantages.reshape(-1)
            b_returns = returns.reshape(-1)
            b_values = values.reshape(-1)
            b_old_means = old_means.reshape(-1, act_dim)

            stats = []
            for epoch in range(args.update_epochs):
                # Core detail 6: shuffle the whole batch each epoch and split it into minibatches.
                # Permuting once per epoch and then taking contiguous slices (views) does one
                # gather per tensor per epoch instead of one per minibatch.
                b_inds = torch.randperm(batch_size)
                e_obs, e_actions, e_logprobs = b_obs[b_inds], b_actions[b_inds], b_logprobs[b_inds]
                e_advantages, e_returns, e_values = b_advantages[b_inds], b_returns[b_inds], b_values[b_inds]
                e_old_means = b_old_means[b_inds]
                for start in range(0, batch_size, args.minibatch_size):
                    mb = slice(start, start + args.minibatch_size)
                    new_means = agent.actor_mean(e_obs[mb])
                    newlogprob = gaussian_log_prob(e_actions[mb], new_means, agent.actor_logstd)
                    logratio = newlogprob - e_logprobs[mb]
                    ratio = logratio.exp()  # r_t(theta), paper eq. (6)

                    mb_advantages = e_advantages[mb]
                    if args.norm_adv:
                        # Core detail 7: normalize the advantages of each minibatch.
                        mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)

                    kl = gaussian_kl(e_old_means[mb], old_logstd, new_means, agent.actor_logstd)
                    pg_loss = kl_penalty_loss(ratio, mb_advantages, kl, beta)
                    v_loss = value_loss(agent.get_value(e_obs[mb]), e_values[mb], e_returns[mb], args.clip_coef, args.clip_vloss)
                    # The entropy of a Gaussian with state-independent std does not depend on s.
                    entropy = (agent.actor_logstd + 0.5 * math.log(2 * math.pi * math.e)).sum()
                    # Core detail 10, paper eq. (9) with L^KLPEN in place of L^CLIP, signs flipped to minimize.
                    loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss

                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if args.clip_grad_norm:
                        # Core detail 11: clip the global norm of all gradients together.
                        nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm, foreach=True)
                    optimizer.step()

                    # Core detail 12: debug statistics. approx_kl is the (r - 1) - log r
                    # estimator of KL[old, new] (http://joschu.net/blog/kl-approx.html). Nothing is
                    # clipped here: clipfrac is the fraction of ratios that PPO-Clip would clip.
                    with torch.no_grad():
                        stats.append(torch.stack([
                            pg_loss, v_loss, entropy, (-logratio).mean(), ((ratio - 1) - logratio).mean(),
                            ((ratio - 1.0).abs() > args.clip_coef).float().mean(),
                        ]))  # fmt: skip

            # ADAPT BETA (paper §4): d is the exact KL between pi_old and the updated policy, averaged
            # over the whole batch, measured once after all K epochs.
            with torch.no_grad():
                kl_batch = gaussian_kl(b_old_means, old_logstd, agent.actor_mean(b_obs), agent.actor_logstd).mean().item()
            writer.add_scalar("losses/beta", beta, global_step)  # the beta this update used
            writer.add_scalar("losses/kl", kl_batch, global_step)
            if args.adaptive_beta:
                beta = adapt_beta(beta, kl_batch, args.kl_target)

            # LOGGING: the mean over every minibatch of the update, not the last minibatch's value.
            pg_mean, v_mean, ent_mean, old_kl_mean, kl_mean, clipfrac_mean = torch.stack(stats).mean(0).tolist()
            var_y = b_returns.var()
            explained_var = float("nan") if var_y == 0 else (1 - (b_returns - b_values).var() / var_y).item()
            sps = int((global_step - start_step) / (time.time() - start_time))
            writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"], global_step)
            writer.add_scalar("charts/SPS", sps, global_step)
            writer.add_scalar("losses/policy_loss", pg_mean, global_step)
            writer.add_scalar("losses/value_loss", v_mean, global_step)
            writer.add_scalar("losses/entropy", ent_mean, global_step)
            writer.add_scalar("losses/old_approx_kl", old_kl_mean, global_step)
            writer.add_scalar("losses/approx_kl", kl_mean, global_step)
            writer.add_scalar("losses/clipfrac", clipfrac_mean, global_step)
            writer.add_scalar("losses/explained_variance", explained_var, global_step)

            # CHECKPOINT
            snapshot = make_checkpoint(args, agent, optimizer, global_step, iteration, beta)
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


def evaluate(args):
    """Run the deterministic policy (the Gaussian's mean) of --eval-checkpoint with its saved statistics."""
    import gymnasium as gym

    checkpoint = load_checkpoint(args.eval_checkpoint)
    train_args = args_from_checkpoint(checkpoint, args)
    torch.set_num_threads(args.torch_threads)
    if args.capture_video:
        os.environ.setdefault("MUJOCO_GL", "egl")  # render headless, without a display
    env = gym.make(train_args.env_id, render_mode="rgb_array" if args.capture_video else None)
    if args.capture_video:
        video_dir = os.path.join(os.path.dirname(os.path.abspath(args.eval_checkpoint)), "videos-eval")
        env = gym.wrappers.RecordVideo(env, video_dir, episode_trigger=lambda episode: True, name_prefix="eval")
    agent = Agent(env.observation_space.shape[0], env.action_space.shape[0], norm_obs=train_args.norm_obs)
    agent.load_state_dict(checkpoint["agent"])

    returns = []
    with torch.inference_mode():
        for episode in range(args.eval_episodes):
            raw_obs, _ = env.reset(seed=args.seed + episode)
            done, episode_return = False, 0.0
            while not done:
                # The statistics are frozen: evaluation must not change the normalization.
                action = agent.actor_mean(torch.from_numpy(agent.normalize_obs(raw_obs)))
                raw_obs, reward, term, trunc, _ = env.step(np.clip(action.numpy(), env.action_space.low, env.action_space.high))
                episode_return += float(reward)
                done = term or trunc
            returns.append(episode_return)
    env.close()
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
