"""Shared fixtures: every check written once and run over every ppo_*.py script that exists."""

import dataclasses
import functools
import importlib.util
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = sorted(p.name for p in ROOT.glob("ppo_*.py"))

# How to run each script on a tiny budget: an env it accepts, a few hundred steps with a small
# batch, a run of 32 iterations of 64 steps (long enough to interrupt), and an env it must reject
# for its action space. The tiny runs have an entropy bonus (Atari's default; the MuJoCo scripts default to
# none), so that the loss's check sees the sign of its term. A new script must add its line here, or
# test_every_script_is_configured fails. Each list of flags is written as its command line, split on spaces.
TINY = {
    "ppo_continuous.py": {
        "env_id": "Hopper-v5",
        "tiny": "--num-steps 64 --minibatch-size 32 --update-epochs 2 --total-timesteps 128 --ent-coef 0.01".split(),
        "interruptible": "--num-steps 64 --minibatch-size 16 --update-epochs 10 --total-timesteps 2048".split(),
        "wrong_action_space_env": "CartPole-v1",
    },
    "ppo_atari.py": {
        "env_id": "BreakoutNoFrameskip-v4",
        # 3 iterations of 4 envs x 96 steps: long enough for random games of Breakout to end
        "tiny": "--num-envs 4 --num-steps 96 --minibatch-size 128 --update-epochs 1 --total-timesteps 1152".split(),
        "interruptible": (
            "--num-envs 1 --num-steps 64 --minibatch-size 32 --update-epochs 1 --total-timesteps 2048"
        ).split(),
        "wrong_action_space_env": "Hopper-v5",
    },
    # ppo_rlhf.py makes its own text: no env, so the checks of envs, episodes and videos skip it (needs_env), and
    # tests/test_rlhf.py runs its command line on this tiny budget: 4 PPO iterations of 16 responses.
    "ppo_rlhf.py": {
        "no_env": "ppo_rlhf.py has no gymnasium env, episodes or videos: tests/test_rlhf.py checks its command line",
        "tiny": (
            "--d-model 16 --n-layer 1 --n-head 2 --response-length 16 --sft-steps 60 --sft-learning-rate 0.01"
            " --rm-pairs 128 --rm-epochs 1 --rm-batch-size 32 --total-episodes 64 --batch-size 16 --minibatch-size 8"
            " --update-epochs 2"
        ).split(),
    },
    "ppo_kl_penalty.py": {
        "env_id": "Hopper-v5",
        "tiny": "--num-steps 64 --minibatch-size 32 --update-epochs 2 --total-timesteps 128 --ent-coef 0.01".split(),
        "interruptible": "--num-steps 64 --minibatch-size 16 --update-epochs 10 --total-timesteps 2048".split(),
        "wrong_action_space_env": "CartPole-v1",
    },
}

# The TensorBoard scalars every gym script logs, under the names CleanRL and most tools read.
EXPECTED_SCALARS = {
    "charts/episodic_return",
    "charts/episodic_length",
    "charts/learning_rate",
    "charts/SPS",
    "losses/policy_loss",
    "losses/value_loss",
    "losses/entropy",
    "losses/approx_kl",
    "losses/old_approx_kl",
    "losses/clipfrac",
    "losses/explained_variance",
    "losses/loss",
}


def needs_env(script):
    """Skip a check of gymnasium envs, episodes or videos for a script that has none, saying why."""
    if "no_env" in TINY[script]:
        pytest.skip(TINY[script]["no_env"])


@functools.cache
def load_script(name):
    """Import a script by file name, as a module, without running its __main__."""
    spec = importlib.util.spec_from_file_location(name[: -len(".py")], ROOT / name)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module


def scripts_with(attribute):
    """The scripts that define `attribute`, for checks of math that only some scripts have."""
    return [name for name in SCRIPTS if hasattr(load_script(name), attribute)]


@pytest.fixture(autouse=True)
def writes_nothing_in_the_checkout():
    """Every test writes under the folders pytest gives it (tmp_path): a run folder left in the checkout's runs/
    fails the test that made it."""
    runs = ROOT / "runs"
    before = set(os.listdir(runs)) if runs.is_dir() else set()
    yield
    left = (set(os.listdir(runs)) if runs.is_dir() else set()) - before
    assert not left, f"the test left {sorted(left)} in {runs}: give it a folder under tmp_path"


@pytest.fixture(params=SCRIPTS)
def script(request):
    return request.param


# The tests run two at a time on two cores (pytest -n 2), so each script gets one torch thread: two threads each
# would contend for the cores and slow every run down.
ONE_THREAD = ["--torch-threads", "1"]


def call_main(module, argv, monkeypatch, starts=("train",), checked=True):
    """module.main() on this command line, with what it would start replaced (the functions named in `starts`; and
    main()'s signal handlers, which would stay in pytest's way): the Args the last one started got, None if none
    started, or the code main() exited with (a refusal). checked=False replaces check_args too."""
    import torch

    started = []
    monkeypatch.setattr(sys, "argv", [module.SCRIPT, *map(str, argv)])
    for name in starts:
        if hasattr(module, name):
            monkeypatch.setattr(module, name, lambda args, *rest: started.append(args))
    if not checked:
        monkeypatch.setattr(module, "check_args", lambda args: None)
    monkeypatch.setattr(module.signal, "signal", lambda *args: None)
    threads = torch.get_num_threads()
    try:
        module.main()
    except SystemExit as e:
        return e.code
    finally:
        torch.set_num_threads(threads)
    return started[-1] if started else None


def run_cli(script, *args, cwd, timeout=300, check=True):
    """Run a script's real command line in `cwd`, with one torch thread; return the CompletedProcess."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}  # MUJOCO_GL is left to the scripts' own default
    proc = subprocess.run(
        [sys.executable, str(ROOT / script), *map(str, args), *ONE_THREAD],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"{script} {' '.join(map(str, args))} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        )
    return proc


def train_tiny(script, cwd, name="run", *extra):
    """A tiny training run of a script in cwd/name: (run_dir, CompletedProcess)."""
    cfg = TINY[script]
    run_dir = cwd / name
    return run_dir, run_cli(script, "--env-id", cfg["env_id"], *cfg["tiny"], "--run-dir", run_dir, *extra, cwd=cwd)


def script_at(commit, script, folder):
    """The script as it was at `commit`, written to folder/<script> (for the checkpoints an earlier version wrote)."""
    proc = subprocess.run(["git", "show", f"{commit}:{script}"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, f"this test needs the git history of commit {commit}: {proc.stderr}"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / script).write_text(proc.stdout)
    return folder / script


def roll_back(path):
    """Rolls the checkpoint at path back one iteration, for a resumed run to train again; returns what it saved."""
    import torch

    checkpoint = torch.load(path, weights_only=True)
    checkpoint["iteration"] -= 1
    checkpoint["global_step"] -= checkpoint["global_step"] // (checkpoint["iteration"] + 1)
    torch.save(checkpoint, path)
    return checkpoint


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """The tiny training run of a script, made once per test process and shared by the tests that only read it
    (a test that writes to its checkpoint works on a copy): tiny_run(script) -> (run_dir, CompletedProcess)."""
    runs = {}

    def get(script):
        if script not in runs:
            runs[script] = train_tiny(script, tmp_path_factory.mktemp(script[: -len(".py")]))
        return runs[script]

    return get


def tb_scalars(run_dir):
    """All scalars in a run directory's TensorBoard event files: {tag: [(step, value), ...]}."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def signal_at_checkpoint(proc, checkpoint, sig, wait):
    """Send `sig` to a training process (or a runner) once `checkpoint` exists; return its (stdout, stderr).
    If a check fails, SIGTERM stops it, and a runner its runs, so that no process is left behind."""
    try:
        deadline = time.time() + wait
        while not checkpoint.exists() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.02)
        assert checkpoint.exists(), f"no checkpoint after {wait} s (exit {proc.poll()})"
        proc.send_signal(sig)
        return proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.communicate(timeout=120)


def rlhf_tiny_args(tmp_path, name="run", **overrides):
    """The Args of ppo_rlhf.py's TINY run, for its train() in the test's process."""
    rlhf = load_script("ppo_rlhf.py")
    flags = TINY["ppo_rlhf.py"]["tiny"]
    names = [flag[2:].replace("-", "_") for flag in flags[::2]]
    types = {f.name: type(getattr(rlhf.Args(), f.name)) for f in dataclasses.fields(rlhf.Args)}
    values = {name: types[name](value) for name, value in zip(names, flags[1::2], strict=True)}
    return rlhf.Args(**{**values, "torch_threads": 1, "run_dir": str(tmp_path / name), **overrides})


def fake_run(folder, env_id, variant, seed, last100_mean, steps=100_000, meta=()):
    """A results CSV whose last 100 episodes average last100_mean, after 50 early episodes that must not count; `meta`:
    more (key, value) lines for its header."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from results import write_csv

    returns = [-1e4] * 50 + [last100_mean - 1.0, last100_mean + 1.0] * 50
    rows = [((i + 1) * steps // len(returns), r, 10) for i, r in enumerate(returns)]
    header = [
        ("command", "test"),
        ("env_id", env_id),
        ("seed", seed),
        ("global_step", steps),
        ("commit", "abc1234"),
        ("versions", "test versions"),
        ("machine", "test machine"),
        ("wall_time_s", "60"),
        *meta,
    ]
    write_csv(folder / f"{env_id}__{variant}__seed{seed}.csv", header, rows)


def fake_random(results, env_id, returns):
    """results/random/<env_id>.csv with the random policy's episodes scoring `returns`."""
    path = results / "random" / f"{env_id}.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# command: test", "episode,episodic_return,episodic_length"]
    lines += [f"{i},{r},1" for i, r in enumerate(returns)]
    path.write_text("\n".join(lines) + "\n")


# roboschool_humanoid.py's tasks, read from the simulator's own state by name (tests/test_roboschool_*.py and
# tests/test_bullet_body.py), not through the module's helpers.
TASKS = ["HumanoidForward", "HumanoidFlagrun", "HumanoidFlagrunHarder"]
DT = 0.0165
BODIES = "torso lwaist pelvis right_thigh right_shin right_foot left_thigh left_shin left_foot".split()
BODIES += "right_upper_arm right_lower_arm left_upper_arm left_lower_arm".split()
JOINTS = "abdomen_z abdomen_y abdomen_x right_hip_x right_hip_z right_hip_y right_knee left_hip_x left_hip_z".split()
JOINTS += "left_hip_y left_knee right_shoulder1 right_shoulder2 right_elbow left_shoulder1 left_shoulder2".split()
JOINTS += ["left_elbow"]
# Where Bullet put the link of each body other than the torso: the centre of the body's last geom if it is a capsule
# (by the geom's name), else the body's origin (the feet, and the lower arms whose last geom is the hand).
PART_GEOMS = "lwaist butt right_thigh1 right_shin1 left_thigh1 left_shin1 right_uarm1 left_uarm1".split()
PART_ORIGINS = "right_foot left_foot right_lower_arm left_lower_arm".split()
ROW0 = np.array([0])  # an env's one body, as the rules' methods take their bodies: a row index array


def make(task, seed=0):
    import gymnasium as gym

    sys.path.insert(0, str(ROOT))  # the module beside the scripts, by its id
    env = gym.make(f"roboschool_humanoid:{task}-v0").unwrapped
    env.reset(seed=seed)
    return env


def body_xy(env):
    """The body's x, y: the mean of Roboschool's 29 parts, the 12 links (PART_GEOMS, PART_ORIGINS) and the 17 joints'
    anchors, by name."""
    data = env.data
    parts = [data.geom(name).xpos for name in PART_GEOMS] + [data.body(name).xpos for name in PART_ORIGINS]
    parts += [data.joint(name).xanchor for name in JOINTS]
    return np.mean(parts, axis=0)[:2]


def torso_z(env):
    """The height of the torso's Bullet frame: the centre of its last geom, uwaist, 0.12 m below its origin."""
    return env.data.geom("uwaist").xpos[2]


def torso_velocity(env):
    """The world velocity of the torso's Bullet frame, as MuJoCo computes it for the uwaist geom's centre."""
    import mujoco

    data = mujoco.MjData(env.model)
    data.qpos[:], data.qvel[:] = env.data.qpos, env.data.qvel
    mujoco.mj_forward(env.model, data)
    velocity = np.zeros(6)  # angular, then linear
    mujoco.mj_objectVelocity(env.model, data, mujoco.mjtObj.mjOBJ_GEOM, env.model.geom("uwaist").id, velocity, 0)
    return velocity[3:]


def stand(env, qpos):
    """Put the body back where `qpos` has it, at rest, keeping the cube's state (the rules see a standing body)."""
    data = env.data
    n = 7 + len(JOINTS)
    data.qpos[:n] = qpos[:n]
    data.qvel[: n - 1] = 0.0
    env.set_state(data.qpos.copy(), data.qvel.copy())


def restart_potential(env):
    """The potential of the state as it is now, as a step would have left it."""
    env.bodies.humanoid_state(ROW0)
    env.bodies.potential[0] = env.bodies.calc_potential(ROW0)[0]


def step_from(env, qpos, qvel, action):
    env.set_state(qpos, qvel)
    restart_potential(env)
    return env.step(action)
