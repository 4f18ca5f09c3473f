"""PPO-Clip for Atari, in one file: Proximal Policy Optimization (Schulman et al. 2017, arXiv:1707.06347) as §6.4 ran
it: a CNN shared by policy and value in L^{CLIP+VF+S} (eq. 9), 8 actors, and alpha annealing the learning rate and the
clip range (Table 5). Where the paper is silent we follow "The 37 Implementation Details of PPO" (Huang et al. 2022):
"core detail N" (of 13) and "atari detail N" (of 9). `diff ppo_continuous.py ppo_atari.py` shows what Atari changes.

    python ppo_atari.py                                  # Breakout, 10M steps (40M frames)
    python ppo_atari.py --env-id PongNoFrameskip-v4 --total-timesteps 1000000
    python ppo_atari.py --compile                        # the same algorithm, compiled by torch.compile
    python ppo_atari.py --help                           # every flag, with its default

The paper's 10M steps are a job for a GPU (auto picks CUDA when there is one).
"""

from __future__ import annotations

import math
import os
import re
import signal
import sys
import time
from collections import deque
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
from torch.distributions import Categorical


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]  # the name of this experiment, part of the run directory's name
    seed: int = 1  # seed of torch and of the environments
    device: str = "auto"  # torch device: auto, cpu, cuda, cuda:1, ... (auto is cuda when there is one)
    compile: bool = False  # apply torch.compile to the policy step and the minibatch update (it compiles during the first iterations)
    torch_threads: int = 2  # torch CPU threads (the CNN's convolutions use a second thread; the MLP scripts use 1)
    run_dir: str | None = None  # where TensorBoard logs and the checkpoint go (None: runs/{env_id}__{exp_name}__{seed}__{time})
    capture_video: bool = False  # film games 0, 1, 8, 27, ... of the first env in training, and every evaluation game, in colour
    # Algorithm: the paper's Atari settings (Table 5) where it gives one, else the implementation detail cited
    env_id: str = "BreakoutNoFrameskip-v4"  # an Atari game, by a gymnasium ALE id (BreakoutNoFrameskip-v4, ALE/Breakout-v5) or a name (Breakout); always played as NoFrameskip-v4 (no sticky actions)
    total_timesteps: int = 10_000_000  # total agent steps over all envs, rounded down to whole batches (paper: 10M steps = 40M frames)
    max_episode_frames: int = 108_000  # truncate a game after this many frames of play (30 minutes at 60 Hz)
    fire_on_life_loss: bool = False  # also press FIRE after a lost life, as baselines' wrappers did (ale-py: only at a game's start)
    learning_rate: float = 2.5e-4  # Adam step size at the start (paper: 2.5e-4 x alpha)
    num_envs: int = 8  # number of parallel actors N (paper: 8)
    num_steps: int = 128  # steps per actor in each rollout, the horizon T (paper: 128)
    anneal_lr: bool = True  # anneal the learning rate with alpha, linearly to 0 (paper Table 5; core detail 4)
    anneal_clip: bool = True  # anneal the clip range with alpha, 0.1 x alpha (paper Table 5; CleanRL keeps it fixed)
    gamma: float = 0.99  # discount factor gamma (paper: 0.99)
    gae_lambda: float = 0.95  # GAE lambda (paper: 0.95)
    minibatch_size: int = 256  # minibatch size (paper: 32 x 8 = 256); must divide --num-envs x --num-steps
    update_epochs: int = 3  # epochs K over each rollout (paper: 3; CleanRL: 4)
    norm_adv: bool = True  # normalize advantages per minibatch (core detail 7)
    clip_coef: float = 0.1  # clip range epsilon of L^CLIP at the start (paper: 0.1 x alpha), also the value loss's, fixed
    clip_vloss: bool = True  # clip the value loss around the old values by --clip-coef, not annealed (core detail 9; not in eq. 9)
    ent_coef: float = 0.01  # entropy bonus coefficient c2 (paper: 0.01)
    vf_coef: float = 1.0  # c1 of eq. 9, on the squared error (V - V_targ)^2 (paper: 1; CleanRL's 0.5 on half of it is 0.25 here)
    clip_grad_norm: bool = True  # clip the global gradient norm (core detail 11)
    max_grad_norm: float = 0.5  # the maximum global gradient norm, when clipping
    save_every: int = 50  # write the checkpoint every this many iterations of N x T steps (it is also written at the end and on Ctrl-C)
    resume: str | None = None  # continue the run saved in this checkpoint; its hyperparameters come from the checkpoint
    eval_checkpoint: str | None = None  # evaluate the policy of this checkpoint instead of training
    eval_episodes: int = 10  # number of games for --eval-checkpoint


# THE MATH
def compute_gae(rewards, values, next_values, terminations, truncations, gamma, gae_lambda):
    """Generalized advantage estimation, paper eq. (11)-(12), over [T, N] tensors.

    next_values[t] is V of the observation that step t reached: after a time-limit truncation, the
    final observation's, bootstrapped (Pardo et al. 2018; the paper's code and CleanRL treat it as a
    termination); no advantage flows across an episode's end. The returns A + V are the value
    function's TD(lambda) targets (core detail 5).

    >>> one = torch.ones(3, 1)
    >>> adv, ret = compute_gae(one, 0 * one, 0 * one, torch.tensor([[0.], [0.], [1.]]), 0 * one, 0.5, 1.0)
    >>> adv.flatten().tolist()  # discounted reward-to-go with gamma = 0.5: 1 + .5 + .25, 1 + .5, 1
    [1.75, 1.5, 1.0]
    """
    terminations, dones = terminations.float(), torch.maximum(terminations.float(), truncations.float())
    # Eq. (12), for all t at once: delta_t = r_t + gamma V(s_{t+1}) - V(s_t), with V = 0 after a termination.
    deltas = rewards + gamma * (1.0 - terminations) * next_values - values
    # Eq. (11), backwards in time: A_t = delta_t + gamma lambda A_{t+1}, restarted where an episode ended.
    advantages, lastgaelam = torch.zeros_like(rewards), torch.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        lastgaelam = deltas[t] + gamma * gae_lambda * (1.0 - dones[t]) * lastgaelam
        advantages[t] = lastgaelam
    return advantages, advantages + values


def clipped_surrogate_loss(ratio, advantages, clip_coef):
    """Minus L^CLIP, paper eq. (7): -E[min(r A, clip(r, 1 - eps, 1 + eps) A)] (core detail 8).

    >>> clipped_surrogate_loss(torch.tensor([1.5, 0.5]), torch.tensor([1.0, 1.0]), 0.2)  # -(min(1.5, 1.2) + min(.5, .8)) / 2
    tensor(-0.8500)
    """
    surr1 = ratio * advantages
    surr2 = torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef) * advantages
    return -torch.min(surr1, surr2).mean()


def value_loss(newvalue, oldvalue, returns, clip_coef, clip_vloss=True):
    """L^VF of paper eq. (9), the squared error (V - V_targ)^2 against the returns, optionally clipped (core detail 9).

    The clipped form is baselines' ppo2, not the paper's: the larger of the errors of the new value and
    of the old value moved at most clip_coef towards it. Engstrom et al. (2020) found no gain in it."""
    v_loss_unclipped = (newvalue - returns) ** 2
    if not clip_vloss:
        return v_loss_unclipped.mean()
    v_clipped = oldvalue + torch.clamp(newvalue - oldvalue, -clip_coef, clip_coef)
    return torch.max(v_loss_unclipped, (v_clipped - returns) ** 2).mean()


# ENVIRONMENT
def game_name(env_id):
    """'BreakoutNoFrameskip-v4', 'ALE/Breakout-v5', 'Breakout', 'breakout' -> the ROM name in ALE/<Name>-v5's spec, or None."""
    import ale_py
    import gymnasium as gym  # importing ale_py registered its games
    ale_py.ALEInterface.setLoggerMode(ale_py.LoggerMode.Error)  # no banner on stderr
    name = re.sub(r"(NoFrameskip|Deterministic)?(-v\d+)?$", "", env_id.split("/")[-1]).lower()
    games = {key[4:-3].lower(): spec.kwargs["game"] for key, spec in gym.registry.items() if key.startswith("ALE/") and key.endswith("-v5")}
    return games.get(name, name if name in games.values() else None)


def make_envs(args, num_envs=None, training=True):
    """ale-py's vector env: C++ emulators on their own threads, with atari details 1-5 and 7 built in (6 is in train())."""
    import ale_py
    return ale_py.AtariVectorEnv(
        game_name(args.env_id), num_envs or args.num_envs, num_threads=min(num_envs or args.num_envs, os.cpu_count() or 1),
        max_num_frames_per_episode=args.max_episode_frames,  # a time limit: a truncation, whose value is bootstrapped
        repeat_action_probability=0.0,  # no sticky actions: the paper's NoFrameskip-v4 games are deterministic but for the noops
        noop_max=30,  # atari detail 1: up to 30 no-ops at the start of each game
        frameskip=4, maxpool=True,  # atari detail 2: repeat each action for 4 frames, max-pool the last two
        life_loss_info=training,  # atari detail 3: a lost life ends an episode for learning, but the game (and its score) go on
        use_fire_reset=True,  # atari detail 4: press FIRE at the start of each game that needs it (after a lost life: see train())
        img_height=84, img_width=84, grayscale=True, stack_num=4,  # atari details 5 and 7: 84x84 grayscale, the last 4 frames
        reward_clipping=False,  # atari detail 6 is in train(), where the raw score is logged too
        autoreset_mode="SameStep",  # as in ppo_continuous.py: the step that ends a game returns the next one's first frame
    )  # fmt: skip


def game_over(terminations, truncations, frame_numbers, new_frame_numbers):
    """Which envs ended a whole game: ALE's episode_frame_number restarts at a new game, and counts on after a lost life."""
    return (terminations | truncations) & (new_frame_numbers < frame_numbers)


def write_video(env_id, reset_frames, actions, path):
    """Replay a game in a new emulator, writing every frame in colour (210x160) at 60 Hz to an mp4. Without sticky actions
    the same reset (ale-py's: FIRE if the game has it, then no-ops, reset_frames in all) and actions play the same game."""
    import ale_py
    import imageio.v2 as imageio
    ale = ale_py.ALEInterface()
    ale.setFloat("repeat_action_probability", 0.0)
    ale.loadROM(ale_py.roms.get_rom_path(game_name(env_id)))
    ale.reset_game()  # as ale-py's reset does: some games (BeamRider) play differently without it
    action_set, fire = ale.getMinimalActionSet(), [ale_py.Action.FIRE] * (ale_py.Action.FIRE in ale.getMinimalActionSet())
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with imageio.get_writer(path, fps=60, macro_block_size=1) as video:
        for action in fire + [ale_py.Action.NOOP] * (reset_frames - len(fire)) + [action_set[a] for a in actions for _ in range(4)]:
            ale.act(action)
            video.append_data(ale.getScreenRGB())


# AGENT
def layer_init(layer, std=math.sqrt(2), bias_const=0.0):
    # Core detail 2: orthogonal weights with gain sqrt(2) for hidden layers, constant 0 biases.
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    def __init__(self, num_actions):
        super().__init__()
        # Atari detail 8: baselines' Nature-DQN CNN, shared by policy and value (§6.4 names [Mni+16]'s smaller one); gains 0.01, 1 (core detail 2).
        self.network = nn.Sequential(
            layer_init(nn.Conv2d(4, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(), layer_init(nn.Linear(64 * 7 * 7, 512)), nn.ReLU(),
        )  # fmt: skip
        self.actor = layer_init(nn.Linear(512, num_actions), std=0.01)
        self.critic = layer_init(nn.Linear(512, 1), std=1.0)

    def get_value(self, obs):
        return self.critic(self.network(obs / 255.0)).squeeze(-1)

    def get_action_and_value(self, obs, action=None):
        """A sampled action (or the given one), its log-prob under pi(.|s), the entropy, and V(s)."""
        hidden = self.network(obs / 255.0)  # atari detail 9: scale the uint8 frames to [0, 1] in the network
        probs = Categorical(logits=self.actor(hidden), validate_args=False)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action), probs.entropy(), self.critic(hidden).squeeze(-1)


# TRAINING
def train(args):
    from torch.utils.tensorboard import SummaryWriter
    # A new run, or the run of --resume, continued with the hyperparameters of its checkpoint.
    checkpoint = load_checkpoint(args.resume) if args.resume else None
    args = resumed_args(checkpoint, args) if checkpoint else args
    run_dir = args.run_dir or f"runs/{args.env_id}__{args.exp_name}__{args.seed}__{int(time.time())}"
    checkpoint_path, device = os.path.join(run_dir, "checkpoint.pt"), torch.device(("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device)
    T, N = args.num_steps, args.num_envs
    batch_size, num_iterations = N * T, args.total_timesteps // (N * T)
    torch.manual_seed(args.seed)  # with the envs' seeds below, all the randomness: on the CPU, one seed gives one run
    torch.set_num_threads(args.torch_threads)

    envs = make_envs(args)  # core detail 1: N envs stepped together, with same-step autoreset
    agent = Agent(envs.single_action_space.n).to(device)
    # Core detail 3: Adam with eps 1e-5. The lr is a tensor: annealing it changes a number, not what --compile built.
    optimizer = torch.optim.Adam(agent.parameters(), lr=torch.tensor(args.learning_rate, device=device), eps=1e-5, fused=True)
    global_step, start_iteration = 0, 1
    if checkpoint:
        agent.load_state_dict(checkpoint["agent"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        torch.set_rng_state(checkpoint["torch_rng_state"])
        global_step, start_iteration = checkpoint["global_step"], checkpoint["iteration"] + 1
        print(f"resuming {run_dir} at step {global_step:,} (iteration {checkpoint['iteration']})")

    def update(mb_obs, mb_actions, mb_logprobs, mb_advantages, mb_returns, mb_values, clip_coef):
        """One minibatch step of gradient descent on minus L^{CLIP+VF+S}, paper eq. (9)."""
        _, newlogprob, entropy, newvalue = agent.get_action_and_value(mb_obs, mb_actions)
        logratio = newlogprob - mb_logprobs
        ratio = logratio.exp()  # r_t(theta), paper eq. (6)
        if args.norm_adv:  # core detail 7: normalize the advantages of each minibatch
            mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)
        pg_loss = clipped_surrogate_loss(ratio, mb_advantages, clip_coef)
        v_loss = value_loss(newvalue, mb_values, mb_returns, args.clip_coef, args.clip_vloss)  # the fixed clip range, never annealed
        entropy = entropy.mean()
        loss = pg_loss - args.ent_coef * entropy + args.vf_coef * v_loss  # minus eq. (9), to minimize (core detail 10)
        optimizer.zero_grad()
        loss.backward()
        if args.clip_grad_norm:  # core detail 11: clip the global norm of all gradients together
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
        optimizer.step()
        # Core detail 12: approx_kl is the (r - 1) - log r estimator of KL[old, new] (joschu.net/blog/kl-approx.html).
        stats = dict(policy_loss=pg_loss, value_loss=v_loss, entropy=entropy, old_approx_kl=(-logratio).mean(),
                     approx_kl=((ratio - 1) - logratio).mean(), clipfrac=((ratio - 1.0).abs() > clip_coef).float().mean(), loss=loss)
        return {name: stat.detach() for name, stat in stats.items()}

    policy = agent.get_action_and_value
    if args.compile:
        torch._inductor.config.fallback_random = True  # sample with torch's own generator, as eager code does
        policy, update = torch.compile(policy), torch.compile(update)

    # Rollout storage: T steps of N envs. Frames stay uint8 until the network.
    obs, actions = torch.zeros((T, N, 4, 84, 84), dtype=torch.uint8, device=device), torch.zeros((T, N), dtype=torch.long, device=device)
    logprobs, rewards, values, terminations, truncations, final_values = torch.zeros((6, T, N), device=device)

    # Env i of run --seed s, from step g on, is seeded (s + g) N + i: two runs from step 0 share no env; a resume starts new games.
    next_obs, infos = envs.reset(seed=(args.seed + global_step) * N + np.arange(N))
    next_obs, frame_numbers, lost_life = torch.as_tensor(next_obs, device=device), infos["episode_frame_number"], np.zeros(N, dtype=bool)
    # Env 0's game so far, its reset's frames and its actions, which --capture-video replays in colour when the game ends.
    episode_return, episode_length, games_of_env0, video_reset_frames, video_actions = np.zeros(N), np.zeros(N, dtype=np.int64), 0, frame_numbers[0], []
    fire = next((i for i, a in enumerate(envs.ale.get_action_set()) if a.name == "FIRE" and args.fire_on_life_loss), None)  # --fire-on-life-loss
    # On --resume, purge_step drops what the run logged after its checkpoint: its curves go on without a fold.
    writer = SummaryWriter(run_dir, purge_step=global_step + 1 if checkpoint else None)
    writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + "\n".join(f"|{k}|{v}|" for k, v in asdict(args).items()))
    recent_returns, stop = deque(maxlen=100), []
    start_time, start_step, last_print, diverged = time.time(), global_step, 0.0, False
    # Ctrl-C and SIGTERM (say, a job scheduler's stop) only set a flag, which the loop checks.
    previous_handlers = {sig: signal.signal(sig, lambda signum, frame: stop.append(signum)) for sig in (signal.SIGINT, signal.SIGTERM)}

    # ALGORITHM 1: for iteration = 1, 2, ...
    for iteration in range(start_iteration, num_iterations + 1):
        # Paper §6.4, Table 5: alpha falls linearly from 1 to 0, scaling the lr (core detail 4) and L^CLIP's clip range (not V's, which ppo2 annealed too).
        alpha = 1.0 - (iteration - 1.0) / num_iterations
        optimizer.param_groups[0]["lr"].fill_(alpha * args.learning_rate if args.anneal_lr else args.learning_rate)
        clip_coef = torch.tensor(alpha * args.clip_coef if args.anneal_clip else args.clip_coef, device=device)

        # ROLLOUT: run the policy pi_theta_old in N environments for T timesteps.
        with torch.no_grad():
            for step in range(T):
                global_step += N
                obs[step] = next_obs
                action, logprobs[step], _, values[step] = policy(next_obs)
                if fire is not None and lost_life.any():  # the env, not the policy, presses FIRE; the batch keeps it as if pi_old chose it
                    action = torch.where(torch.as_tensor(lost_life, device=device), fire, action)
                    _, logprobs[step], _, values[step] = policy(next_obs, action)
                actions[step] = action
                next_obs, reward, term, trunc, infos = envs.step(action.cpu().numpy())
                next_obs = torch.as_tensor(next_obs, device=device)
                # Atari detail 6: learn from the sign of the reward; log the raw score of the whole game, over all lives.
                terminations[step], truncations[step], rewards[step] = torch.as_tensor(term), torch.as_tensor(trunc), torch.as_tensor(np.sign(reward))
                episode_return, episode_length = episode_return + reward, episode_length + 1
                finished, frame_numbers = game_over(term, trunc, frame_numbers, infos["episode_frame_number"]), infos["episode_frame_number"]
                lost_life = term & ~finished  # atari detail 3: a termination within a game is a lost life
                video_actions.append(int(action[0]))
                for i in np.flatnonzero(trunc):  # bootstrap from the true final observation of an episode cut by the time limit
                    final_values[step, i] = agent.get_value(torch.as_tensor(infos["final_obs"][i][None], device=device))[0]
                for i in np.flatnonzero(finished):
                    recent_returns.append(episode_return[i])
                    writer.add_scalar("charts/episodic_return", episode_return[i], global_step)
                    writer.add_scalar("charts/episodic_length", episode_length[i], global_step)
                    episode_return[i], episode_length[i] = 0.0, 0
                    if i == 0:  # the first env's game is over: film the cubes, games 0, 1, 8, 27, ... (replayed: see write_video)
                        if args.capture_video and games_of_env0 == round(games_of_env0 ** (1 / 3)) ** 3:
                            write_video(args.env_id, video_reset_frames, video_actions, f"{run_dir}/videos/step-{global_step}-game-{games_of_env0}.mp4")
                        games_of_env0, video_actions, video_reset_frames = games_of_env0 + 1, [], frame_numbers[0]

            # ADVANTAGES: next_values[t] = V(s_{t+1}), the last one eq. (10)'s bootstrap V(s_T), or V(final observation) where an episode was truncated.
            next_values = torch.cat([values[1:], agent.get_value(next_obs)[None]])
            next_values = torch.where(truncations.bool(), final_values, next_values)
            advantages, returns = compute_gae(rewards, values, next_values, terminations, truncations, args.gamma, args.gae_lambda)

        # UPDATE: K epochs of minibatch gradient descent on the flattened batch.
        b_obs, b_actions, b_logprobs = obs.reshape(-1, 4, 84, 84), actions.reshape(-1), logprobs.reshape(-1)
        b_advantages, b_returns, b_values, update_stats = advantages.reshape(-1), returns.reshape(-1), values.reshape(-1), []
        for epoch in range(args.update_epochs):
            b_inds = torch.randperm(batch_size, device=device)  # core detail 6: a new shuffle each epoch
            for start in range(0, batch_size, args.minibatch_size):
                mb_inds = b_inds[start : start + args.minibatch_size]
                update_stats.append(update(b_obs[mb_inds], b_actions[mb_inds], b_logprobs[mb_inds], b_advantages[mb_inds],
                                           b_returns[mb_inds], b_values[mb_inds], clip_coef))  # fmt: skip

        # LOGGING: the mean over every minibatch of the update, not the last minibatch's value.
        losses = {name: torch.stack([stats[name] for stats in update_stats]).mean().item() for name in update_stats[0]}
        losses["explained_variance"] = (1 - (b_returns - b_values).var() / b_returns.var()).item()
        sps = int((global_step - start_step) / (time.time() - start_time))
        writer.add_scalar("charts/learning_rate", optimizer.param_groups[0]["lr"].item(), global_step)
        writer.add_scalar("charts/SPS", sps, global_step)
        writer.add_scalar("charts/clip_coef", clip_coef.item(), global_step)
        for name, value in losses.items():
            writer.add_scalar(f"losses/{name}", value, global_step)
        if time.time() - last_print > 10 or iteration == num_iterations:
            last_print, recent = time.time(), f"{np.mean(recent_returns):.1f}" if recent_returns else "n/a"
            print(f"step {global_step:,}/{num_iterations * batch_size:,} | SPS {sps} | return (last {len(recent_returns)}) {recent}"
                  f" | ETA {(num_iterations * batch_size - global_step) / max(sps, 1) / 60:.1f} min", flush=True)  # fmt: skip

        # CHECKPOINT, unless the run diverged: then the last finite checkpoint stays on disk.
        diverged = not (math.isfinite(losses["policy_loss"] + losses["value_loss"]) and all(p.isfinite().all() for p in agent.parameters()))
        if not diverged and (stop or iteration % args.save_every == 0 or iteration == num_iterations):
            writer.flush()  # the curve on disk reaches at least the checkpoint's step
            save_checkpoint(checkpoint_path, args, agent, optimizer, global_step, iteration)
        if diverged or stop:
            break

    for sig, handler in previous_handlers.items():
        signal.signal(sig, handler)
    envs.close()
    writer.close()
    if diverged:
        sys.exit(f"{os.path.basename(__file__)}: error: the loss or the weights are not finite after iteration {iteration}; "
                 f"try a smaller --learning-rate (the last finite checkpoint, if any, is {checkpoint_path})")  # fmt: skip
    if stop:
        print(f"stopped: saved step {global_step:,} to {checkpoint_path}; continue with --resume {checkpoint_path}")
        sys.exit(130)
    print(f"saved {checkpoint_path}")
    return agent, run_dir


# EVALUATION
def evaluate(args):
    """Play --eval-episodes whole games with the sampled policy of --eval-checkpoint (its argmax can stall) and report the scores."""
    checkpoint = load_checkpoint(args.eval_checkpoint)
    train_args, device = resumed_args(checkpoint, args), torch.device(("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device)
    envs = make_envs(train_args, num_envs=1, training=False)  # whole games: no life-loss terminations
    agent = Agent(envs.single_action_space.n).to(device)
    agent.load_state_dict(checkpoint["agent"])
    torch.manual_seed(args.seed)
    returns = []
    for game in range(args.eval_episodes):
        (next_obs, infos), done, game_return, actions = envs.reset(seed=args.seed + game), False, 0.0, []
        while not done:
            with torch.no_grad():
                action, _, _, _ = agent.get_action_and_value(torch.as_tensor(next_obs, device=device))
            actions.append(int(action[0]))
            next_obs, reward, term, trunc, _ = envs.step(action.cpu().numpy())
            game_return, done = game_return + float(reward[0]), bool(term[0] or trunc[0])
        returns.append(game_return)
        if args.capture_video:
            write_video(train_args.env_id, infos["episode_frame_number"][0], actions, f"{train_args.run_dir}/videos-eval/eval-game-{game}.mp4")
    envs.close()
    print(f"eval {train_args.env_id} step {checkpoint['global_step']:,}: return {np.mean(returns):.1f} ± {np.std(returns):.1f} over {len(returns)} episodes")
    return returns


# MACHINERY: checkpoints and argument checks. A resumed run takes how to run it (RUNTIME_FIELDS) from the command line.
RUNTIME_FIELDS = ("device", "compile", "torch_threads", "capture_video", "save_every", "resume", "eval_checkpoint", "eval_episodes")


def resumed_args(checkpoint, args):
    run_dir = os.path.dirname(os.path.abspath(args.resume or args.eval_checkpoint))
    return Args(**{**checkpoint["args"], **{k: getattr(args, k) for k in RUNTIME_FIELDS}, "run_dir": run_dir})


def save_checkpoint(path, args, agent, optimizer, global_step, iteration):
    # Tensors, numbers and strings, loadable with torch.load(weights_only=True); written, then renamed, atomically.
    torch.save({"format": "ppo-checkpoint-v1", "script": os.path.basename(__file__), "args": asdict(args), "agent": agent.state_dict(),
                "optimizer": optimizer.state_dict(), "global_step": global_step, "iteration": iteration,
                "torch_rng_state": torch.get_rng_state()}, f"{path}.tmp")  # fmt: skip
    os.replace(f"{path}.tmp", path)


def load_checkpoint(path):
    """A checkpoint of this script, loaded on the CPU; a ValueError with a one-line reason if it is not one."""
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"cannot read checkpoint {path!r}: it is corrupt or not a checkpoint ({type(e).__name__})") from None
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != "ppo-checkpoint-v1" or checkpoint.get("script") != os.path.basename(__file__):
        raise ValueError(f"{path!r} is not a checkpoint written by {os.path.basename(__file__)}")
    return checkpoint


def check_args(args):
    """Reject bad input before anything heavy loads, with a one-line reason (a ValueError)."""
    flag, batch = lambda name: "--" + name.replace("_", "-"), args.num_envs * args.num_steps  # noqa: E731
    for name, value in asdict(args).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{flag(name)} must be a finite number, got {value}")
    for name in ("total_timesteps", "num_envs", "num_steps", "minibatch_size", "update_epochs", "save_every", "eval_episodes",
                 "torch_threads", "learning_rate", "clip_coef", "max_grad_norm", "max_episode_frames"):  # fmt: skip
        if getattr(args, name) <= 0:
            raise ValueError(f"{flag(name)} must be positive, got {getattr(args, name)}")
    for name, low, high in (("gamma", 0, 1), ("gae_lambda", 0, 1), ("vf_coef", 0, math.inf), ("ent_coef", 0, math.inf)):
        if not low <= getattr(args, name) <= high:
            raise ValueError(f"{flag(name)} must be in [{low}, {high}], got {getattr(args, name)}")
    if batch % args.minibatch_size:
        raise ValueError(f"--minibatch-size {args.minibatch_size} does not divide the batch of --num-envs x --num-steps = {batch}")
    if args.resume is None and args.eval_checkpoint is None and args.total_timesteps < batch:
        raise ValueError(f"--total-timesteps {args.total_timesteps} is less than one batch of {batch} steps")
    if args.device != "auto" and not (args.device == "cpu" or (args.device.startswith("cuda") and torch.cuda.is_available())):
        raise ValueError(f"--device {args.device} is not available here; use auto or cpu")
    if args.run_dir is not None and os.path.isfile(args.run_dir):
        raise ValueError(f"--run-dir {args.run_dir} is a file, not a directory")
    if args.resume is None and args.run_dir is not None and os.path.isdir(args.run_dir) and any("tfevents" in f for f in os.listdir(args.run_dir)):
        raise ValueError(f"--run-dir {args.run_dir} already holds a run: continue it with --resume {args.run_dir}/checkpoint.pt, or pick a new directory")
    if args.resume is not None or args.eval_checkpoint is not None:
        args = resumed_args(load_checkpoint(args.resume or args.eval_checkpoint), args)
    if game_name(args.env_id) is None:
        raise ValueError(f"unknown env id {args.env_id!r}: ale-py has no such game, and this script trains only Atari games, with their discrete action space")


def main():
    import tyro
    args = tyro.cli(Args)
    try:
        check_args(args)
    except ValueError as e:
        print(f"{os.path.basename(__file__)}: error: {e}", file=sys.stderr)  # one line, before anything starts
        sys.exit(2)
    evaluate(args) if args.eval_checkpoint is not None else train(args)


if __name__ == "__main__":
    main()
