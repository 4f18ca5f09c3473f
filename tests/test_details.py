"""Every implementation detail of train() has a test that fails without it: each row of the README's table of the
"37 implementation details" (Huang et al. 2022), and the bootstrap of a truncated episode from V(final observation).

Each script trains once, in this process, on a tiny budget, with what train() calls wrapped so that its inputs are
recorded: the module-level math (compute_gae, the policy and value losses), the Agent, Adam, torch.randperm,
clip_grad_norm_ and the vector env. The tests check those records against what each detail implies, computed here
independently: running statistics in closed form, log-probs and KLs from torch.distributions, the value from the
network's own layers. Nothing depends on train()'s local names or layout, so the checks survive a rewrite of it.
"""

import copy
import inspect
import math

import numpy as np
import pytest
import torch
from conftest import ROOT, SCRIPTS, load_script, scripts_with, tb_scalars
from torch.distributions import Categorical, Normal, kl_divergence

# The tiny runs: 2 iterations of 2 envs x 64 steps, so that a second iteration sees annealing, a new shuffle and
# beta's adaptation. The MuJoCo runs have an entropy bonus so that its sign shows in the gradient; Atari's c1 is
# not 1, so that a dropped coefficient shows. Their step sizes are 10 and 20 times the defaults, so that some
# ratios leave the clip range (clipfrac > 0). A new script must add its line here (see the first test).
RUNS = {
    "ppo_continuous.py": dict(env_id="Hopper-v5", ent_coef=0.01, learning_rate=3e-3),
    "ppo_kl_penalty.py": dict(env_id="Hopper-v5", ent_coef=0.01, learning_rate=3e-3, kl_target=1.0),  # beta halves
    "ppo_atari.py": dict(
        env_id="BreakoutNoFrameskip-v4", learning_rate=5e-3, minibatch_size=64, vf_coef=0.5, max_episode_frames=240
    ),
}
COMMON = dict(num_envs=2, num_steps=64, minibatch_size=32, update_epochs=2, total_timesteps=256, torch_threads=1)
# ppo_rlhf.py trains a language model, not on envs: its details (the score at the EOS, the KL penalty to pi_SFT, the
# mask) are checked the same way, in their own file.
ELSEWHERE = {"ppo_rlhf.py": "tests/test_rlhf_details.py"}
RECORDED = [script for script in SCRIPTS if script not in ELSEWHERE]
MUJOCO = scripts_with("make_env")
ATARI = scripts_with("game_over")
KL = scripts_with("kl_penalty_loss")
CLIP = [script for script in scripts_with("clipped_surrogate_loss") if script in RECORDED]
# MuJoCo episodes cut at 20 steps: random Hopper falls (a termination) in about half of them.
TIME_LIMIT = 20
# One outlier in env 0's observation and one in its reward, late enough (after 200 samples) that the normalized
# value of each exceeds 10 (at most sqrt(n - 1) standard deviations from the mean of n samples).
OBS_SPIKE_STEP = 100
REWARD_SPIKE_STEP = 90


def test_every_script_is_recorded():
    assert set(SCRIPTS) <= set(RUNS) | set(ELSEWHERE), (
        f"add the new script's details to tests/test_details.py: {set(SCRIPTS) - set(RUNS) - set(ELSEWHERE)}"
    )
    assert all((ROOT / path).is_file() for path in ELSEWHERE.values())


# RECORDING: wrappers that note what train() passes through the stable surface, and change nothing.
def detach(value):
    if isinstance(value, torch.Tensor):
        return value.detach().clone()
    if isinstance(value, tuple):
        return tuple(detach(v) for v in value)
    return value


def grads(loss, module):
    """d loss / d parameters, without touching .grad, and keeping the graph for train()'s own backward."""
    params = list(module.parameters())
    found = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g.detach().clone() for g, p in zip(found, params, strict=True)]


class Record:
    def __init__(self, script, module):
        self.script = script
        self.module = module
        self.phase = "train"  # then "eval", for Atari's evaluation
        self.calls = {}  # module function -> its calls
        self.agents = []
        self.rollout = []  # the Agent's calls that sampled an action
        self.minibatches = []  # its calls that evaluated the batch's actions
        self.optimizers = []
        self.steps = []  # Adam's steps
        self.clips = []
        self.perms = []
        self.env_inits = []
        self.env_reset = []
        self.env_steps = []

    def wrap(self, name):
        """module.<name>, recording its bound arguments, its output, the gradient of a loss, and for compute_gae the
        agent as it is then: the policy that collected the rollout."""
        fn = getattr(self.module, name)
        log = self.calls.setdefault(name, [])
        signature = inspect.signature(fn)

        def wrapper(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            out = fn(*args, **kwargs)
            entry = {k: detach(v) for k, v in bound.arguments.items()}
            entry["differentiable"] = {k for k, v in bound.arguments.items() if getattr(v, "requires_grad", False)}
            entry["out"] = detach(out)
            if isinstance(out, torch.Tensor) and out.requires_grad:
                entry["grads"] = grads(out, self.agents[-1])
            if name == "compute_gae":
                entry["agent"] = copy.deepcopy(self.agents[-1])
            log.append(entry)
            return out

        return wrapper

    def __getitem__(self, name):
        return self.calls.get(name, [])


def install(mp, rec):
    """Wrap, on their modules, everything train() looks up when it runs."""
    import gymnasium as gym

    module = rec.module
    for name in ("compute_gae", "clipped_surrogate_loss", "kl_penalty_loss", "value_loss"):
        if hasattr(module, name):
            mp.setattr(module, name, rec.wrap(name))

    class RecordedAgent(module.Agent):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            if rec.phase == "train":
                rec.agents.append(self)

        def get_action_and_value(self, obs, action=None):
            out = super().get_action_and_value(obs, action)
            if rec.phase != "train":
                return out
            action_out, logprob, probs, value = out
            if action is None:  # the rollout samples; the update evaluates the actions of the batch
                rec.rollout.append(
                    dict(obs=detach(obs), action=detach(action_out), logprob=detach(logprob), value=detach(value))
                )
            else:
                entropy = probs.entropy()
                rec.minibatches.append(
                    dict(
                        obs=detach(obs),
                        action=detach(action),
                        logprob=detach(logprob),
                        entropy=detach(entropy),
                        value=detach(value),
                        entropy_grads=grads(entropy.mean(), self),
                    )
                )
            return out

    mp.setattr(module, "Agent", RecordedAgent)

    class RecordingAdam(torch.optim.Adam):
        def __init__(self, params, *args, **kwargs):
            params = list(params)
            super().__init__(params, *args, **kwargs)
            rec.optimizers.append(dict(optimizer=self, params=params, **kwargs))

        def step(self, closure=None):
            params = [p for group in self.param_groups for p in group["params"]]
            rec.steps.append(
                dict(
                    lr=float(self.param_groups[0]["lr"]),
                    params=[p.detach().clone() for p in params],
                    grads=[torch.zeros_like(p) if p.grad is None else p.grad.detach().clone() for p in params],
                )
            )
            return super().step(closure)

    mp.setattr(torch.optim, "Adam", RecordingAdam)

    clip_grad_norm_ = torch.nn.utils.clip_grad_norm_
    clip_signature = inspect.signature(clip_grad_norm_)

    def recording_clip(*args, **kwargs):
        bound = clip_signature.bind(*args, **kwargs)
        bound.apply_defaults()
        params = list(bound.arguments["parameters"])
        bound.arguments["parameters"] = params
        rec.clips.append(dict(bound.arguments))
        return clip_grad_norm_(*bound.args, **bound.kwargs)

    mp.setattr(torch.nn.utils, "clip_grad_norm_", recording_clip)

    randperm = torch.randperm

    def recording_randperm(n, *args, **kwargs):
        out = randperm(n, *args, **kwargs)
        rec.perms.append(out.clone())
        return out

    mp.setattr(torch, "randperm", recording_randperm)

    def note_step(actions, out):
        obs, reward, term, trunc, infos = out
        ended = np.flatnonzero(np.asarray(term) | np.asarray(trunc))
        final = {i: np.array(infos["final_obs"][i]) for i in ended}
        rec.env_steps.append(
            dict(
                actions=np.array(actions),
                obs=np.array(obs),
                reward=np.array(reward, dtype=np.float64),
                term=np.array(term),
                trunc=np.array(trunc),
                final_obs=final,
                frame=np.array(infos.get("episode_frame_number", [])),
            )
        )

    if module in [load_script(s) for s in MUJOCO]:
        sync = gym.vector.SyncVectorEnv

        class RecordedSyncVectorEnv(sync):
            def __init__(self, env_fns, *args, **kwargs):
                env_fns = list(env_fns)
                bound = inspect.signature(sync.__init__).bind(self, env_fns, *args, **kwargs)
                bound.apply_defaults()
                rec.env_inits.append(dict(phase=rec.phase, **bound.arguments))
                super().__init__(env_fns, *args, **kwargs)

            def reset(self, *args, **kwargs):
                obs, infos = super().reset(*args, **kwargs)
                rec.env_reset.append(np.array(obs))
                return obs, infos

            def step(self, actions):
                out = super().step(actions)
                note_step(actions, out)
                return out

        mp.setattr(gym.vector, "SyncVectorEnv", RecordedSyncVectorEnv)
        make_env = module.make_env
        created = []
        Outliers = outliers_wrapper()

        def short_make_env(env_id, *args, **kwargs):
            env = Outliers(gym.wrappers.TimeLimit(make_env(env_id, *args, **kwargs), TIME_LIMIT), first=not created)
            created.append(env)
            return env

        mp.setattr(module, "make_env", short_make_env)
    else:
        import ale_py

        ale = ale_py.AtariVectorEnv

        class RecordedAtariVectorEnv(ale):
            """ale-py's env, recorded, with its rewards made 3 r - 2 every 5th step: values whose sign is not
            themselves, positive and negative, that train() must clip for learning and log as they are."""

            def __init__(self, *args, **kwargs):
                bound = inspect.signature(ale.__init__).bind(self, *args, **kwargs)
                bound.apply_defaults()
                rec.env_inits.append(dict(phase=rec.phase, **bound.arguments))
                super().__init__(*args, **kwargs)
                self.steps = 0

            def reset(self, *args, **kwargs):
                obs, infos = super().reset(*args, **kwargs)
                if rec.phase == "train":
                    rec.env_reset.append((np.array(obs), np.array(infos["episode_frame_number"])))
                return obs, infos

            def step(self, actions):
                obs, reward, term, trunc, infos = super().step(actions)
                self.steps += 1
                reward = 3.0 * np.asarray(reward, dtype=np.float64) - 2.0 * (self.steps % 5 == 0)
                if rec.phase == "train":
                    note_step(actions, (obs, reward, term, trunc, infos))
                return obs, reward, term, trunc, infos

        mp.setattr(ale_py, "AtariVectorEnv", RecordedAtariVectorEnv)


def outliers_wrapper():
    import gymnasium as gym

    class Outliers(gym.Wrapper):
        """In the first env only: one huge observation and one huge reward (see OBS_SPIKE_STEP), in ordinary steps."""

        def __init__(self, env, first):
            super().__init__(env)
            self.first = first
            self.steps = 0
            self.obs_spiked = False
            self.reward_spiked = False

        def step(self, action):
            obs, reward, term, trunc, info = self.env.step(action)
            self.steps += 1
            if self.first and not (term or trunc):
                if self.steps >= OBS_SPIKE_STEP and not self.obs_spiked:
                    obs = obs.copy()
                    obs[0] += 1e3
                    self.obs_spiked = True
                if self.steps >= REWARD_SPIKE_STEP and not self.reward_spiked:
                    reward += 1e3
                    self.reward_spiked = True
            return obs, reward, term, trunc, info

    return Outliers


def record_run(script, tmp_path):
    module = load_script(script)
    rec = Record(script, module)
    with pytest.MonkeyPatch.context() as mp:
        install(mp, rec)
        rec.args = module.Args(**{**COMMON, **RUNS[script]}, run_dir=str(tmp_path / "run"))
        rec.agent, rec.run_dir = module.train(rec.args)
        if script in ATARI:  # evaluation's env too (the checkpoint's 240-frame games are short)
            rec.phase = "eval"
            module.evaluate(
                module.Args(eval_checkpoint=f"{rec.run_dir}/checkpoint.pt", eval_episodes=1, torch_threads=1)
            )
    rec.scalars = tb_scalars(rec.run_dir)
    rec.checkpoint = torch.load(f"{rec.run_dir}/checkpoint.pt", weights_only=True)
    a = rec.args
    rec.T = a.num_steps
    rec.N = a.num_envs
    rec.K = a.update_epochs
    rec.B = rec.T * rec.N
    rec.M = rec.B // a.minibatch_size  # minibatches per epoch
    rec.S = rec.K * rec.M  # optimizer steps per iteration
    rec.I = a.total_timesteps // rec.B  # iterations
    return rec


@pytest.fixture(scope="session")
def recorded(tmp_path_factory):
    runs = {}

    def get(script):
        if script not in runs:
            try:
                runs[script] = record_run(script, tmp_path_factory.mktemp(f"details-{script[:-3]}"))
            except Exception as e:  # a train() that crashes fails every test of its script, but runs only once
                runs[script] = e
        if isinstance(runs[script], Exception):
            raise runs[script]
        return runs[script]

    return get


# INDEPENDENT REFERENCES
def running_stats(batches):
    """RunningMeanStd's mean and var after these batches, in closed form: its prior is mean 0, var 1, count 1e-4."""
    x = np.concatenate([np.asarray(b, dtype=np.float64) for b in batches])
    prior = 1e-4
    n = len(x)
    total = prior + n
    mean = x.mean(0) * n / total
    var = (prior + x.var(0) * n + x.mean(0) ** 2 * prior * n / total) / total
    return mean, var


def normalized(raw, mean, var, clip=True):
    z = (raw - mean) / np.sqrt(var + 1e-8)
    return torch.as_tensor(np.clip(z, -10.0, 10.0) if clip else z, dtype=torch.float32)


def value_of(rec, agent, obs):
    """V(s) from the network's layers: the MLP critic, or the critic head on the CNN of frames scaled to [0, 1]."""
    with torch.no_grad():
        if rec.script in ATARI:
            return agent.critic(agent.network(obs.float() / 255.0)).squeeze(-1)
        return agent.critic(obs).squeeze(-1)


def policy_of(rec, agent, obs):
    """pi(.|s) from the network's layers: a diagonal Gaussian with a state-independent std, or a softmax."""
    if rec.script in ATARI:
        return Categorical(logits=agent.actor(agent.network(obs.float() / 255.0)))
    return Normal(agent.actor_mean(obs), agent.actor_logstd.exp())


def with_params(agent, params):
    scratch = copy.deepcopy(agent)
    with torch.no_grad():
        for p, value in zip(scratch.parameters(), params, strict=True):
            p.copy_(value)
    return scratch


def iteration(rec, i):
    """Iteration i (from 1) of the run: what the rollout stored, as [T, N, ...], and its compute_gae call."""
    T = rec.T
    rollout = rec.rollout[(i - 1) * T : i * T]
    assert len(rollout) == T, f"the rollout of iteration {i} sampled {len(rollout)} steps, not T = {T}"
    out = {key: torch.stack([r[key] for r in rollout]) for key in ("obs", "action", "logprob", "value")}
    out["gae"] = rec["compute_gae"][i - 1]
    out["env"] = rec.env_steps[(i - 1) * T : i * T]
    return out


def flat(x):
    """[T, N, ...] -> [T N, ...], step-major: the index of step t of env n is t N + n."""
    return x.reshape(-1, *x.shape[2:])


def minibatches(rec):
    """For each optimizer step: (iteration, its flat batch indices) from the epoch's permutation, and what the
    update passed to the Agent, the losses and the optimizer."""
    a = rec.args
    mb = a.minibatch_size
    perms = [p for p in rec.perms if p.numel() == rec.B]
    pg = rec[policy_loss_name(rec)]
    vl = rec["value_loss"]
    assert len(rec.steps) == len(rec.minibatches) == len(pg) == len(vl) == rec.I * rec.S, "one step per minibatch"
    assert len(perms) == rec.I * a.update_epochs, "a new permutation of the batch each epoch"
    for k in range(rec.I * rec.S):
        i, j = divmod(k, rec.S)
        epoch, chunk = divmod(j, rec.M)
        inds = perms[(i * a.update_epochs) + epoch][chunk * mb : (chunk + 1) * mb]
        yield dict(iteration=i + 1, inds=inds, agent_call=rec.minibatches[k], pg=pg[k], vl=vl[k], step=rec.steps[k])


def policy_loss_name(rec):
    return "clipped_surrogate_loss" if rec.script in CLIP else "kl_penalty_loss"


def logged(rec, tag):
    return [value for _, value in sorted(rec.scalars[tag], key=lambda sv: sv[0])]


# THE TRUNCATION BOOTSTRAP
@pytest.mark.parametrize("script", RECORDED)
def test_truncated_episode_bootstraps_from_the_value_of_its_final_observation(script, recorded):
    # next_values[t] at a time-limit truncation is V(final observation), by the policy that collected the rollout,
    # of the observation normalized with the statistics of that step; else V(s_{t+1}), the last V(s_T).
    rec = recorded(script)
    raw = [rec.env_reset[0] if script in MUJOCO else rec.env_reset[0][0]] + [s["obs"] for s in rec.env_steps]
    cut = 0
    for i in range(1, rec.I + 1):
        it = iteration(rec, i)
        agent = it["gae"]["agent"]
        next_values = it["gae"]["next_values"]
        for t in range(rec.T):
            g = (i - 1) * rec.T + t  # the step's index in the run
            step = it["env"][t]
            for n in range(rec.N):
                if step["trunc"][n] and not step["term"][n]:
                    final = step["final_obs"][n]
                    if script in MUJOCO:
                        final = normalized(final, *running_stats(raw[: g + 2]))
                    expected = value_of(rec, agent, torch.as_tensor(final)[None])[0]
                    assert next_values[t, n].item() == pytest.approx(expected.item(), abs=1e-5), (
                        f"iteration {i}, step {t}, env {n}: a truncated episode is not bootstrapped from V(final obs)"
                    )
                    following = it["value"][t + 1, n] if t + 1 < rec.T else next_values[t, n] + 1
                    cut += abs(expected.item() - following.item()) > 1e-3
                elif not step["term"][n]:
                    if t + 1 < rec.T:
                        expected = it["value"][t + 1, n]
                    else:
                        last = torch.as_tensor(step["obs"])
                        if script in MUJOCO:
                            last = normalized(step["obs"], *running_stats(raw[: g + 2]))
                        expected = value_of(rec, agent, last)[n]
                    assert next_values[t, n].item() == pytest.approx(expected.item(), abs=1e-5), (i, t, n)
    assert cut >= 2, "too few truncations whose final value differs from the next episode's first"


# CORE DETAILS
@pytest.mark.parametrize("script", RECORDED)
def test_core1_envs_step_together_with_same_step_autoreset(script, recorded):
    rec = recorded(script)
    init = [e for e in rec.env_inits if e["phase"] == "train"]
    assert len(init) == 1, "one vector env"
    num_envs = len(init[0]["env_fns"]) if script in MUJOCO else init[0]["num_envs"]
    assert num_envs == rec.N
    mode = init[0]["autoreset_mode"]
    assert getattr(mode, "value", mode) == "SameStep", "the step that ends an episode returns the next one's start"
    assert len(rec.env_steps) == rec.I * rec.T and all(len(s["actions"]) == rec.N for s in rec.env_steps)
    gae = rec["compute_gae"]
    assert len(gae) == rec.I and all(g["rewards"].shape == (rec.T, rec.N) for g in gae)


@pytest.mark.parametrize("script", RECORDED)
def test_core2_orthogonal_init_gains_and_zero_biases(script, recorded):
    # The agent that the first optimizer step found: orthogonal weights scaled by the gain, zero biases.
    rec = recorded(script)
    agent = with_params(rec.agent, rec.steps[0]["params"])

    def layers(module):
        return [m for m in module.modules() if isinstance(m, (torch.nn.Linear, torch.nn.Conv2d))]

    if script in ATARI:
        gains = [(m, math.sqrt(2)) for m in layers(agent.network)] + [(agent.actor, 0.01), (agent.critic, 1.0)]
    else:
        gains = []
        for net, head in ((agent.critic, 1.0), (agent.actor_mean, 0.01)):
            *hidden, last = layers(net)
            gains += [(m, math.sqrt(2)) for m in hidden] + [(last, head)]
    assert len(gains) == 6, "three layers in each MLP; four in the CNN, and two heads"
    for layer, gain in gains:
        w = layer.weight.detach().reshape(layer.weight.shape[0], -1).double()
        gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
        torch.testing.assert_close(gram, gain**2 * torch.eye(len(gram), dtype=torch.float64), atol=1e-5, rtol=1e-4)
        assert torch.count_nonzero(layer.bias) == 0


@pytest.mark.parametrize("script", RECORDED)
def test_core3_adam_with_eps_1e5(script, recorded):
    rec = recorded(script)
    assert len(rec.optimizers) == 1
    optimizer = rec.optimizers[0]["optimizer"]
    assert [id(p) for p in rec.optimizers[0]["params"]] == [id(p) for p in rec.agent.parameters()], "all the weights"
    group = optimizer.param_groups[0]
    assert group["eps"] == 1e-5 and group["betas"] == (0.9, 0.999) and not group["amsgrad"]
    assert rec.checkpoint["optimizer"]["param_groups"][0]["eps"] == 1e-5


@pytest.mark.parametrize("script", RECORDED)
def test_core4_learning_rate_anneals_linearly_to_zero(script, recorded):
    rec = recorded(script)
    lr = rec.args.learning_rate
    expected = [lr * (1 - (k // rec.S) / rec.I) for k in range(rec.I * rec.S)]
    assert [s["lr"] for s in rec.steps] == pytest.approx(expected, rel=1e-6), "Adam's step size at each minibatch"
    assert logged(rec, "charts/learning_rate") == pytest.approx(expected[:: rec.S], rel=1e-6)


@pytest.mark.parametrize("script", RECORDED)
def test_core5_gae_of_the_rollout_and_its_returns_reach_the_losses(script, recorded):
    rec = recorded(script)
    for i in range(1, rec.I + 1):
        it = iteration(rec, i)
        gae = it["gae"]
        assert gae["gamma"] == rec.args.gamma and gae["gae_lambda"] == rec.args.gae_lambda
        torch.testing.assert_close(gae["values"], value_of(rec, gae["agent"], flat(it["obs"])).reshape(rec.T, rec.N))
        torch.testing.assert_close(gae["values"], it["value"])
        terms = torch.as_tensor(np.stack([s["term"] for s in it["env"]]))
        truncs = torch.as_tensor(np.stack([s["trunc"] for s in it["env"]]))
        assert torch.equal(gae["terminations"].bool(), terms) and torch.equal(gae["truncations"].bool(), truncs)
    for mb in minibatches(rec):
        it = iteration(rec, mb["iteration"])
        _, returns = it["gae"]["out"]
        torch.testing.assert_close(mb["vl"]["returns"], flat(returns)[mb["inds"]], msg="the value target is A + V")


@pytest.mark.parametrize("script", RECORDED)
def test_core6_a_new_shuffle_each_epoch_of_k_epochs_of_minibatches(script, recorded):
    rec = recorded(script)
    perms = [p for p in rec.perms if p.numel() == rec.B]
    assert all(torch.equal(p.sort().values, torch.arange(rec.B)) for p in perms)
    assert len({tuple(p.tolist()) for p in perms}) == len(perms), "the same order twice"
    for mb in minibatches(rec):
        it = iteration(rec, mb["iteration"])
        assert len(mb["inds"]) == rec.args.minibatch_size
        torch.testing.assert_close(mb["agent_call"]["obs"], flat(it["obs"])[mb["inds"]], msg="the epoch's permutation")
        torch.testing.assert_close(mb["agent_call"]["action"], flat(it["action"])[mb["inds"]])


@pytest.mark.parametrize("script", RECORDED)
def test_core7_advantages_normalized_per_minibatch(script, recorded):
    rec = recorded(script)
    for mb in minibatches(rec):
        advantages, _ = iteration(rec, mb["iteration"])["gae"]["out"]
        raw = flat(advantages)[mb["inds"]]
        torch.testing.assert_close(mb["pg"]["advantages"], (raw - raw.mean()) / (raw.std() + 1e-8))


@pytest.mark.parametrize("script", RECORDED)
def test_core8_policy_objective_of_the_ratio_to_pi_old(script, recorded):
    # r = pi_theta(a|s) / pi_old(a|s) of the batch's actions, differentiable in theta; L^CLIP with the clip range
    # epsilon (Atari: 0.1 alpha, Table 5).
    rec = recorded(script)
    for mb in minibatches(rec):
        i = mb["iteration"]
        it = iteration(rec, i)
        old = policy_of(rec, it["gae"]["agent"], flat(it["obs"])[mb["inds"]])
        new = policy_of(rec, with_params(rec.agent, mb["step"]["params"]), mb["agent_call"]["obs"])
        action = mb["agent_call"]["action"]
        logratio = new.log_prob(action) - old.log_prob(action)
        if script in MUJOCO:
            logratio = logratio.sum(-1)
        torch.testing.assert_close(mb["pg"]["ratio"], logratio.exp().detach(), atol=1e-5, rtol=1e-4)
        assert "ratio" in mb["pg"]["differentiable"] and "advantages" not in mb["pg"]["differentiable"]
        assert any(g.abs().sum() > 0 for g in mb["pg"]["grads"]), "the policy loss does not depend on theta"
        if script in CLIP:
            alpha = 1 - (i - 1) / rec.I if getattr(rec.args, "anneal_clip", False) else 1.0
            assert float(mb["pg"]["clip_coef"]) == pytest.approx(alpha * rec.args.clip_coef)


@pytest.mark.parametrize("script", RECORDED)
def test_core9_value_loss_clipped_around_the_old_values(script, recorded):
    rec = recorded(script)
    for mb in minibatches(rec):
        it = iteration(rec, mb["iteration"])
        assert mb["vl"]["clip_vloss"] is True and float(mb["vl"]["clip_coef"]) == rec.args.clip_coef, "never annealed"
        torch.testing.assert_close(mb["vl"]["oldvalue"], flat(it["value"])[mb["inds"]], msg="V_old of the rollout")
        torch.testing.assert_close(mb["vl"]["newvalue"], mb["agent_call"]["value"])
        assert mb["vl"]["differentiable"] == {"newvalue"}


def loss_gradient(rec, mb):
    """The gradient of minus eq. (9), -(L^CLIP - c1 L^VF + c2 S), from the gradients of its three terms."""
    c1, c2 = rec.args.vf_coef, rec.args.ent_coef
    return [
        pg + c1 * v - c2 * s
        for pg, v, s in zip(mb["pg"]["grads"], mb["vl"]["grads"], mb["agent_call"]["entropy_grads"], strict=True)
    ]


def global_norm(tensors):
    return torch.sqrt(sum((t.double() ** 2).sum() for t in tensors)).item()


@pytest.mark.parametrize("script", RECORDED)
def test_core10_the_gradient_is_that_of_eq9(script, recorded):
    # The step's gradient is that of -(L^CLIP - c1 L^VF + c2 S), scaled by the gradient clip, in every tensor.
    rec = recorded(script)
    for k, mb in enumerate(minibatches(rec)):
        expected, got = loss_gradient(rec, mb), mb["step"]["grads"]
        scale = (
            sum((g.double() * e.double()).sum() for g, e in zip(got, expected, strict=True))
            / global_norm(expected) ** 2
        )
        assert 0 < scale <= 1 + 1e-5
        for (name, _), g, e in zip(rec.agent.named_parameters(), got, expected, strict=True):
            torch.testing.assert_close(g, scale.float() * e, atol=1e-6, rtol=1e-3, msg=f"step {k}, {name}")


@pytest.mark.parametrize("script", RECORDED)
def test_core11_global_gradient_norm_clipped_to_max_grad_norm(script, recorded):
    rec = recorded(script)
    max_norm = rec.args.max_grad_norm
    clipped = 0
    assert len(rec.clips) == len(rec.steps)
    for clip in rec.clips:
        assert clip["max_norm"] == max_norm and clip["norm_type"] == 2
        assert [id(p) for p in clip["parameters"]] == [id(p) for p in rec.agent.parameters()], "all weights together"
    for mb in minibatches(rec):
        norm = global_norm(loss_gradient(rec, mb))
        assert global_norm(mb["step"]["grads"]) == pytest.approx(min(norm, max_norm), rel=1e-4)
        clipped += norm > max_norm
    assert clipped, "no gradient was large enough to clip"


@pytest.mark.parametrize("script", RECORDED)
def test_core12_approx_kl_and_clipfrac_are_logged(script, recorded):
    rec = recorded(script)
    stats = {"approx_kl": [], "old_approx_kl": [], "clipfrac": []}
    for mb in minibatches(rec):
        ratio = mb["pg"]["ratio"].double()
        eps = float(mb["pg"].get("clip_coef", rec.args.clip_coef))  # the KL script: what L^CLIP would have clipped
        stats["approx_kl"].append(((ratio - 1) - ratio.log()).mean().item())
        stats["old_approx_kl"].append((-ratio.log()).mean().item())
        stats["clipfrac"].append(((ratio - 1).abs() > eps).double().mean().item())
    for name, values in stats.items():
        expected = np.reshape(values, (rec.I, rec.S)).mean(1)
        assert logged(rec, f"losses/{name}") == pytest.approx(expected, rel=1e-4, abs=1e-7), name
    assert min(logged(rec, "losses/approx_kl")) > 0 and max(logged(rec, "losses/clipfrac")) > 0


@pytest.mark.parametrize("script", RECORDED)
def test_logged_losses_are_the_means_over_minibatches(script, recorded):
    rec = recorded(script)
    c1, c2 = rec.args.vf_coef, rec.args.ent_coef
    terms = {"policy_loss": [], "value_loss": [], "entropy": [], "loss": []}
    for mb in minibatches(rec):
        terms["policy_loss"].append(mb["pg"]["out"].item())
        terms["value_loss"].append(mb["vl"]["out"].item())
        terms["entropy"].append(mb["agent_call"]["entropy"].mean().item())
        terms["loss"].append(terms["policy_loss"][-1] + c1 * terms["value_loss"][-1] - c2 * terms["entropy"][-1])
    for name, values in terms.items():
        assert logged(rec, f"losses/{name}") == pytest.approx(np.reshape(values, (rec.I, rec.S)).mean(1), rel=1e-5)


@pytest.mark.parametrize("script", MUJOCO)
def test_core13_policy_and_value_networks_are_separate(script, recorded):
    rec = recorded(script)
    agent = rec.agent
    actor = {id(p) for p in agent.actor_mean.parameters()} | {id(agent.actor_logstd)}
    critic = {id(p) for p in agent.critic.parameters()}
    assert not actor & critic and actor | critic == {id(p) for p in agent.parameters()}
    for mb in minibatches(rec):  # no gradient of the value loss in the policy, nor of the policy's in the value
        for p, v, pg, s in zip(
            agent.parameters(), mb["vl"]["grads"], mb["pg"]["grads"], mb["agent_call"]["entropy_grads"], strict=True
        ):
            assert not (v if id(p) in actor else pg + s).any()


# CONTINUOUS DETAILS
def rollout_policies(rec):
    """For every rollout step: pi_old(.|s) from the layers, and the sampled action, the log-prob and entropy it gave."""
    for i in range(1, rec.I + 1):
        it = iteration(rec, i)
        with torch.no_grad():
            pi = policy_of(rec, it["gae"]["agent"], flat(it["obs"]))
        yield pi, flat(it["action"]), flat(it["logprob"]), it


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous1_actions_are_samples_of_a_gaussian(script, recorded):
    rec = recorded(script)
    z = torch.cat([((action - pi.loc) / pi.scale).flatten() for pi, action, _, _ in rollout_policies(rec)])
    assert len(z) > 500 and abs(z.mean().item()) < 0.15 and abs(z.std().item() - 1) < 0.1, "a ~ N(mean(s), std)"
    assert abs((z.abs() < 1).double().mean().item() - 0.6827) < 0.05, "68% within one std"


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous2_log_std_is_a_state_independent_parameter_starting_at_0(script, recorded):
    rec = recorded(script)
    initial = with_params(rec.agent, rec.steps[0]["params"])
    assert isinstance(rec.agent.actor_logstd, torch.nn.Parameter) and not initial.actor_logstd.any()
    for mb in minibatches(rec):  # the same entropy in every state: that of std = exp(log std) of the parameter
        logstd = with_params(rec.agent, mb["step"]["params"]).actor_logstd.detach()
        entropy = (0.5 + 0.5 * math.log(2 * math.pi) + logstd).sum().expand(rec.args.minibatch_size)
        torch.testing.assert_close(mb["agent_call"]["entropy"], entropy)


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous3_log_probs_sum_over_action_dimensions(script, recorded):
    rec = recorded(script)
    for pi, action, logprob, _ in rollout_policies(rec):
        mean, std = pi.loc, pi.scale
        by_hand = -((action - mean) ** 2) / (2 * std**2) - std.log() - 0.5 * math.log(2 * math.pi)
        torch.testing.assert_close(logprob, by_hand.sum(-1))


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous4_separate_64x64_tanh_mlps(script, recorded):
    rec = recorded(script)
    agent = rec.agent
    x = torch.randn(5, rec.env_reset[0].shape[1])
    for net, out in ((agent.critic, 1), (agent.actor_mean, rec.env_steps[0]["actions"].shape[1])):
        linear = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
        assert [tuple(m.weight.shape) for m in linear] == [(64, x.shape[1]), (64, 64), (out, 64)]
        h = x
        for m in linear[:-1]:
            h = torch.tanh(h @ m.weight.T + m.bias)
        torch.testing.assert_close(net(x), h @ linear[-1].weight.T + linear[-1].bias)


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous5_actions_clipped_for_the_env_only(script, recorded):
    rec = recorded(script)
    sampled = torch.stack([r["action"] for r in rec.rollout]).numpy()
    sent = np.stack([s["actions"] for s in rec.env_steps])
    assert (np.abs(sampled) > 1).mean() > 0.1, "the samples leave the action space"
    np.testing.assert_allclose(sent, np.clip(sampled, -1.0, 1.0), err_msg="Hopper's actions lie in [-1, 1]")
    for pi, action, logprob, _ in rollout_policies(rec):  # the ratio's log-prob is the sample's, unclipped
        torch.testing.assert_close(logprob, pi.log_prob(action).sum(-1))
    batch = torch.cat([mb["agent_call"]["action"] for mb in minibatches(rec)])
    assert (batch.abs() > 1).any(), "the update evaluates the clipped actions, not the samples"


def expected_inputs(rec, clip=True):
    """The observation that each rollout step should feed the network: normalized with the running statistics of
    every observation so far, this one included (reset's and each step's, not the final ones)."""
    raw = [rec.env_reset[0]] + [s["obs"] for s in rec.env_steps]
    return [normalized(raw[g], *running_stats(raw[: g + 1]), clip=clip) for g in range(rec.I * rec.T)]


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous6_observations_normalized_with_running_statistics(script, recorded):
    rec = recorded(script)
    inputs = [r["obs"] for r in rec.rollout]
    for g, (got, expected) in enumerate(zip(inputs, expected_inputs(rec), strict=True)):
        torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5, msg=f"step {g}")
    mean, var = running_stats([rec.env_reset[0]] + [s["obs"] for s in rec.env_steps])
    np.testing.assert_allclose(rec.agent.obs_rms.mean, mean, rtol=1e-6)
    np.testing.assert_allclose(rec.agent.obs_rms.var, var, rtol=1e-6)


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous7_normalized_observations_clipped_to_10(script, recorded):
    rec = recorded(script)
    unclipped = torch.stack(expected_inputs(rec, clip=False))
    assert unclipped.abs().max() > 10.5, "the outlier did not stand out"
    inputs = torch.stack([r["obs"] for r in rec.rollout])
    torch.testing.assert_close(inputs, unclipped.clamp(-10, 10), atol=1e-5, rtol=1e-5)
    batch = torch.stack([mb["agent_call"]["obs"] for mb in minibatches(rec)])
    assert batch.abs().max() == 10.0


def expected_rewards(rec, clip=True):
    """Each raw reward divided by the running std of the discounted return (no mean removed), which restarts at an
    episode's end, then clipped to [-10, 10]: [I T, N]."""
    discounted = np.zeros(rec.N)
    seen = []
    out = []
    for s in rec.env_steps:
        discounted = discounted * rec.args.gamma + s["reward"]
        seen.append(discounted.copy())
        _, var = running_stats(seen)
        scaled = s["reward"] / np.sqrt(var + 1e-8)
        out.append(np.clip(scaled, -10, 10) if clip else scaled)
        discounted[s["term"] | s["trunc"]] = 0.0
    return torch.as_tensor(np.stack(out), dtype=torch.float32)


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous8_rewards_scaled_by_the_std_of_the_discounted_return(script, recorded):
    rec = recorded(script)
    rewards = torch.cat([g["rewards"] for g in rec["compute_gae"]])
    torch.testing.assert_close(rewards, expected_rewards(rec), atol=1e-5, rtol=1e-5)
    # The logged return is the env's own: the sum of the raw rewards of each finished episode.
    returns = np.zeros(rec.N)
    episodes = []
    for s in rec.env_steps:
        returns += s["reward"]
        episodes += list(returns[s["term"] | s["trunc"]])
        returns[s["term"] | s["trunc"]] = 0.0
    assert sorted(logged(rec, "charts/episodic_return")) == pytest.approx(sorted(episodes), rel=1e-5)


@pytest.mark.parametrize("script", MUJOCO)
def test_continuous9_scaled_rewards_clipped_to_10(script, recorded):
    rec = recorded(script)
    unclipped = expected_rewards(rec, clip=False)
    assert unclipped.max() > 10.5, "the outlier did not stand out"
    rewards = torch.cat([g["rewards"] for g in rec["compute_gae"]])
    assert rewards.max() == 10.0
    torch.testing.assert_close(rewards, unclipped.clamp(-10, 10), atol=1e-5, rtol=1e-5)


# ATARI DETAILS: ale-py's vector env does the preprocessing; what train() asks of it, and what train() does itself.
ALE_SETTINGS = {
    "atari1": dict(noop_max=30),
    "atari2": dict(frameskip=4, maxpool=True),
    "atari3": dict(life_loss_info=True, episodic_life=False),
    "atari4": dict(use_fire_reset=True),
    "atari5": dict(img_height=84, img_width=84, grayscale=True),
    "atari6": dict(reward_clipping=False),
    "atari7": dict(stack_num=4),
    "no sticky actions": dict(repeat_action_probability=0.0),
}


@pytest.mark.parametrize("script", ATARI)
@pytest.mark.parametrize("detail", ALE_SETTINGS)
def test_atari_env_settings(script, detail, recorded):
    rec = recorded(script)
    init = [e for e in rec.env_inits if e["phase"] == "train"][0]
    assert {k: init[k] for k in ALE_SETTINGS[detail]} == ALE_SETTINGS[detail]
    assert init["max_num_frames_per_episode"] == rec.args.max_episode_frames


@pytest.mark.parametrize("script", ATARI)
def test_atari2_each_step_is_4_frames(script, recorded):
    rec = recorded(script)
    frames = rec.env_reset[0][1]
    for s in rec.env_steps:
        going_on = s["frame"] > frames
        assert (s["frame"][going_on] == frames[going_on] + 4).all()
        frames = s["frame"]


@pytest.mark.parametrize("script", ATARI)
def test_atari3_a_lost_life_ends_the_episode_for_learning_not_the_game(script, recorded):
    rec = recorded(script)
    frames = rec.env_reset[0][1]
    lost_lives = 0
    for s in rec.env_steps:
        lost_lives += (s["term"] & (s["frame"] > frames)).sum()  # a termination, and the game's frames count on
        frames = s["frame"]
    assert lost_lives >= 2
    terms = torch.as_tensor(np.stack([s["term"] for s in rec.env_steps]))
    assert torch.equal(torch.cat([g["terminations"] for g in rec["compute_gae"]]).bool(), terms)
    evaluation = [e for e in rec.env_inits if e["phase"] == "eval"]
    assert len(evaluation) == 1 and not evaluation[0]["life_loss_info"], "evaluation plays whole games"


def games(rec):
    """The (global_step, score, length) of every game that ended: ALE's frame count restarts with a new game."""
    frames = rec.env_reset[0][1]
    score = np.zeros(rec.N)
    length = np.zeros(rec.N)
    out = []
    for g, s in enumerate(rec.env_steps):
        score, length = score + s["reward"], length + 1
        over = (s["term"] | s["trunc"]) & (s["frame"] < frames)
        out += [((g + 1) * rec.N, score[n], length[n]) for n in np.flatnonzero(over)]
        score[over] = 0.0
        length[over] = 0
        frames = s["frame"]
    return out


@pytest.mark.parametrize("script", ATARI)
def test_atari6_rewards_clipped_to_their_sign_and_the_whole_game_score_logged(script, recorded):
    rec = recorded(script)
    raw = torch.as_tensor(np.stack([s["reward"] for s in rec.env_steps]), dtype=torch.float32)
    assert (raw.abs() > 1).any() and (raw < 0).any()
    torch.testing.assert_close(torch.cat([g["rewards"] for g in rec["compute_gae"]]), raw.sign())
    ended = games(rec)
    assert len(ended) >= 2 and any(score != 0 for _, score, _ in ended)
    for tag, column in (("charts/episodic_return", 1), ("charts/episodic_length", 2)):
        got, expected = sorted(rec.scalars[tag]), sorted((game[0], game[column]) for game in ended)
        assert [step for step, _ in got] == [step for step, _ in expected], f"{tag}: whole games end there"
        assert [value for _, value in got] == pytest.approx([value for _, value in expected]), tag


@pytest.mark.parametrize("script", ATARI)
def test_atari7_the_network_sees_the_last_4_frames(script, recorded):
    rec = recorded(script)
    raw = [rec.env_reset[0][0]] + [s["obs"] for s in rec.env_steps]
    for g, r in enumerate(rec.rollout):
        assert r["obs"].shape == (rec.N, 4, 84, 84) and r["obs"].dtype == torch.uint8
        assert torch.equal(r["obs"], torch.as_tensor(raw[g])), "the env's frames, unchanged until the network"


@pytest.mark.parametrize("script", ATARI)
def test_atari8_the_nature_cnn_shared_by_policy_and_value(script, recorded):
    rec = recorded(script)
    agent = rec.agent
    shapes = [(tuple(m.weight.shape), m.stride) for m in agent.network if isinstance(m, torch.nn.Conv2d)]
    assert shapes == [((32, 4, 8, 8), (4, 4)), ((64, 32, 4, 4), (2, 2)), ((64, 64, 3, 3), (1, 1))]
    linear = [m for m in agent.network if isinstance(m, torch.nn.Linear)]
    assert [tuple(m.weight.shape) for m in linear] == [(512, 3136)]
    assert sum(isinstance(m, torch.nn.ReLU) for m in agent.network) == 4
    shared = {id(p) for p in agent.network.parameters()}
    for mb in minibatches(rec):  # both losses train the shared network
        for p, v, pg in zip(agent.parameters(), mb["vl"]["grads"], mb["pg"]["grads"], strict=True):
            if id(p) in shared:
                assert v.any() and pg.any()


@pytest.mark.parametrize("script", ATARI)
def test_atari9_frames_scaled_to_0_1_in_the_network(script, recorded):
    rec = recorded(script)
    agent = copy.deepcopy(rec.agent)
    obs = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    with torch.no_grad():
        hidden = agent.network(obs.float() / 255.0)
        _, logprob, _, value = agent.get_action_and_value(obs, torch.arange(3))
        torch.testing.assert_close(value, agent.critic(hidden).squeeze(-1))
        torch.testing.assert_close(
            logprob, torch.log_softmax(agent.actor(hidden), -1)[torch.arange(3), torch.arange(3)]
        )
        torch.testing.assert_close(agent.get_value(obs), value)


@pytest.mark.parametrize("script", ATARI)
def test_atari_clip_range_anneals_with_alpha_and_the_value_clip_does_not(script, recorded):
    rec = recorded(script)
    alpha = [1 - i / rec.I for i in range(rec.I)]
    assert logged(rec, "charts/clip_coef") == pytest.approx([rec.args.clip_coef * a for a in alpha])


# THE KL PENALTY
@pytest.mark.parametrize("script", KL)
def test_kl_penalty_is_the_exact_kl_from_pi_old(script, recorded):
    rec = recorded(script)
    for mb in minibatches(rec):
        it = iteration(rec, mb["iteration"])
        old = policy_of(rec, it["gae"]["agent"], flat(it["obs"])[mb["inds"]])
        new = policy_of(rec, with_params(rec.agent, mb["step"]["params"]), mb["agent_call"]["obs"])
        kl = kl_divergence(old, new).sum(-1).detach()
        torch.testing.assert_close(mb["pg"]["kl"], kl, atol=1e-6, rtol=1e-4)
        assert "kl" in mb["pg"]["differentiable"], "the penalty pulls theta, not pi_old"
    assert max(mb["pg"]["kl"].max().item() for mb in minibatches(rec)) > 0


@pytest.mark.parametrize("script", KL)
def test_kl_beta_adapts_after_each_update_to_the_exact_kl_of_the_batch(script, recorded):
    # Paper §4: d = E[KL[pi_old, pi_new]] over the batch after the update; beta / 2 if d < d_targ / 1.5, x 2 if
    # d > 1.5 d_targ; the next update uses it.
    rec = recorded(script)
    target = rec.args.kl_target
    beta = rec.args.init_beta
    betas = []
    kls = []
    snapshots = [g["agent"] for g in rec["compute_gae"]] + [rec.agent]
    for i in range(1, rec.I + 1):
        obs = flat(iteration(rec, i)["obs"])
        with torch.no_grad():
            d = kl_divergence(policy_of(rec, snapshots[i - 1], obs), policy_of(rec, snapshots[i], obs)).sum(-1).mean()
        betas.append(beta)
        kls.append(d.item())
        beta = beta / 2 if d < target / 1.5 else beta * 2 if d > target * 1.5 else beta
    assert len(set(betas)) == rec.I, "beta never changed"
    used = [float(mb["pg"]["beta"]) for mb in minibatches(rec)]
    assert used == pytest.approx(np.repeat(betas, rec.S).tolist())
    assert logged(rec, "losses/beta") == pytest.approx(betas)
    assert logged(rec, "losses/kl") == pytest.approx(kls, rel=1e-2)  # float32's rounding of a small difference
    assert rec.checkpoint["beta"] == pytest.approx(beta)
