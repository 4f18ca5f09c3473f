"""The real command line of every script, on tiny budgets: smoke, determinism, checkpoints,
resume, evaluation, video and bad input."""

import dataclasses
import re
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import (
    EXPECTED_SCALARS,
    ONE_THREAD,
    ROOT,
    SCRIPTS,
    TINY,
    call_main,
    load_script,
    needs_env,
    run_cli,
    scripts_with,
    signal_at_checkpoint,
    tb_scalars,
    train_tiny,
)


def weights(run_dir):
    return torch.load(run_dir / "checkpoint.pt", weights_only=True)["agent"]


def test_every_script_is_configured():
    assert "ppo_continuous.py" in SCRIPTS
    assert set(SCRIPTS) <= set(TINY), f"add the new script to TINY in conftest.py: {set(SCRIPTS) - set(TINY)}"


def test_import_runs_nothing_heavy(script):
    code = (
        f"import sys; sys.path.insert(0, {str(ROOT)!r}); import {script[:-3]}; "
        "print(sorted(m for m in ('mujoco', 'ale_py', 'gymnasium', 'tyro') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120).stdout
    assert out.strip() == "[]"


def test_help_lists_the_flags(script, tmp_path):
    out = run_cli(script, "--help", cwd=tmp_path).stdout
    env_flags = [] if "no_env" in TINY[script] else ["--env-id", "--total-timesteps", "--num-envs", "--num-steps"]
    for flag in [*env_flags, "--seed", "--resume", "--save-every", "--device", "--compile", "--torch-threads"]:
        assert flag in out
    assert "no_env" in TINY[script] or "--eval-checkpoint" in out


def test_smoke_run_logs_and_checkpoints(script, tiny_run):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    run_dir, proc = tiny_run(script)
    tiny = dict(zip(TINY[script]["tiny"][::2], map(float, TINY[script]["tiny"][1::2]), strict=True))
    batch, total = int(tiny.get("--num-envs", 1) * tiny["--num-steps"]), int(tiny["--total-timesteps"])
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert checkpoint["global_step"] == total
    assert "step" in proc.stdout and "SPS" in proc.stdout
    scalars = tb_scalars(run_dir)
    assert EXPECTED_SCALARS <= set(scalars), EXPECTED_SCALARS - set(scalars)
    assert [step for step, _ in scalars["charts/SPS"]] == list(range(batch, total + 1, batch))
    for tag in ["losses/policy_loss", "losses/value_loss", "losses/approx_kl"]:
        assert all(np.isfinite(v) for _, v in scalars[tag])
    # The minimized loss is minus eq. 9, -(L^CLIP - c1 L^VF + c2 S), with the script's c1 and c2 at full weight
    # (that L^VF is the unhalved squared error is test_losses' job).
    args = load_script(script).Args()
    ent_coef = tiny.get("--ent-coef", args.ent_coef)
    assert ent_coef > 0, "without an entropy bonus the check below cannot see the sign of its term"
    for (_, total), (_, pg), (_, v), (_, ent) in zip(
        *(scalars[f"losses/{k}"] for k in ("loss", "policy_loss", "value_loss", "entropy")), strict=True
    ):
        assert total == pytest.approx(pg - ent_coef * ent + args.vf_coef * v, rel=1e-4, abs=1e-6)
    # Nothing is left half-written.
    assert not list(run_dir.glob("*.tmp"))


def test_same_seed_same_result_different_seed_different(script, tmp_path, tiny_run):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    a, _ = tiny_run(script)  # the default seed, 1
    b, _ = train_tiny(script, tmp_path, "b", "--seed", "1")
    c, _ = train_tiny(script, tmp_path, "c", "--seed", "2")
    wa, wb, wc = weights(a), weights(b), weights(c)
    for key, value in wa.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, wb[key]), key
    first_weight = next(key for key in wa if key.endswith("weight"))
    assert not torch.equal(wa[first_weight], wc[first_weight])
    assert tb_scalars(a)["charts/episodic_return"] == tb_scalars(b)["charts/episodic_return"]


def test_seeds_of_different_runs_share_no_env(script, tmp_path, monkeypatch):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    # Gymnasium and ale-py seed env i with s + i when given one seed s: seed 1's second env would be seed 2's first.
    import ale_py
    import gymnasium

    module = load_script(script)
    vector_env = ale_py.AtariVectorEnv if script == "ppo_atari.py" else gymnasium.vector.SyncVectorEnv

    class Started(Exception):
        pass

    seeds = {}

    def reset(self, *, seed=None, options=None):  # note the envs' seeds, then stop the run
        seeds[run] = set((np.asarray(seed) + (np.arange(self.num_envs) if np.ndim(seed) == 0 else 0)).tolist())
        raise Started

    monkeypatch.setattr(vector_env, "reset", reset)
    for run in range(1, 11):
        with pytest.raises(Started):
            module.train(
                module.Args(
                    env_id=TINY[script]["env_id"],
                    seed=run,
                    num_envs=8,
                    torch_threads=1,
                    run_dir=str(tmp_path / str(run)),
                )
            )
    assert all(len(s) == 8 for s in seeds.values()), "the envs of one run have different seeds"
    for a in seeds:
        for b in seeds:
            assert a == b or not seeds[a] & seeds[b], (
                f"runs with --seed {a} and {b} share env seeds {seeds[a] & seeds[b]}"
            )


def test_interrupt_saves_and_resume_continues_the_curve(script, tmp_path):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    cfg = TINY[script]
    run_dir = tmp_path / "run"
    # A run long enough to interrupt: 32 iterations of 64 steps, with a checkpoint every iteration.
    args = [
        sys.executable,
        str(ROOT / script),
        "--env-id",
        cfg["env_id"],
        *cfg["interruptible"],
        "--save-every",
        "1",
        "--run-dir",
        str(run_dir),
        *ONE_THREAD,
    ]
    # A shell without job control starts background jobs with SIGINT ignored, and Python then keeps
    # ignoring it; give the child the default disposition, as a terminal would.
    proc = subprocess.Popen(
        args,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    out, err = signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGINT, wait=120)  # Ctrl-C
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err and "--resume" in out
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    interrupted_at = saved["global_step"]
    assert 0 < interrupted_at < 2048

    resumed = run_cli(script, "--resume", run_dir / "checkpoint.pt", cwd=tmp_path)
    assert f"at step {interrupted_at:,}" in resumed.stdout
    final = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert final["global_step"] == 2048 and final["iteration"] == 32
    # One TensorBoard curve: every iteration's step exactly once, from 64 to 2048.
    steps = [step for step, _ in tb_scalars(run_dir)["charts/SPS"]]
    assert steps == list(range(64, 2049, 64))


def test_checkpoint_holds_optimizer_and_statistics(script, tiny_run):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    run_dir, _ = tiny_run(script)
    module = load_script(script)
    checkpoint = module.load_checkpoint(str(run_dir / "checkpoint.pt"), module.Args())[0]
    assert checkpoint["optimizer"]["state"], "the optimizer's moments are saved"
    if hasattr(module, "RunningMeanStd"):
        obs_rms = checkpoint["agent"]["obs_rms._extra_state"]
        assert obs_rms["count"] > 128 and obs_rms["var"].min() > 0


def test_eval_runs_the_saved_policy_and_films_it(script, tmp_path, tiny_run):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    import imageio.v3 as iio

    run_dir, _ = tiny_run(script)
    out = run_cli(
        script, "--eval-checkpoint", run_dir / "checkpoint.pt", "--eval-episodes", "2", "--capture-video", cwd=tmp_path
    ).stdout
    assert "over 2 episodes" in out and "±" in out
    videos = sorted((run_dir / "videos-eval").glob("*.mp4"))
    assert len(videos) == 2, list(run_dir.rglob("*"))
    frames = np.stack(list(iio.imiter(videos[0])))
    assert frames.ndim == 4 and frames.shape[0] > 1 and frames.shape[-1] == 3
    assert frames.std() > 5, "the video is blank"
    assert np.abs(frames[-1].astype(int) - frames[0].astype(int)).mean() > 0.1, "the video does not move"


def test_eval_uses_the_saved_statistics(script, tmp_path, tiny_run):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    # Two checkpoints that differ only in their normalization statistics must act differently.
    module = load_script(script)
    if not hasattr(module, "RunningMeanStd"):
        pytest.skip(f"{script} normalizes no observations")
    run_dir, _ = tiny_run(script)
    checkpoint = module.load_checkpoint(str(run_dir / "checkpoint.pt"), module.Args())[0]
    checkpoint["agent"]["obs_rms._extra_state"]["mean"] += 5.0
    torch.save(checkpoint, tmp_path / "shifted.pt")
    a = run_cli(script, "--eval-checkpoint", run_dir / "checkpoint.pt", "--eval-episodes", "2", cwd=tmp_path).stdout
    b = run_cli(script, "--eval-checkpoint", tmp_path / "shifted.pt", "--eval-episodes", "2", cwd=tmp_path).stdout
    assert a.split("return")[1] != b.split("return")[1]


BAD_INPUTS = [
    (["--learning-rate", "nan"], "--learning-rate must be a finite number, got nan"),
    (["--learning-rate", "inf"], "--learning-rate must be a finite number, got inf"),
    (["--ent-coef", "nan"], "--ent-coef must be a finite number"),
    (["--max-grad-norm", "nan"], "--max-grad-norm must be a finite number"),
    (["--gamma", "-inf"], "--gamma must be a finite number"),
    (["--learning-rate", "0"], "--learning-rate must be positive"),
    (["--clip-coef", "-0.1"], "--clip-coef must be positive"),
    (["--gamma", "1.5"], "--gamma must be in [0, 1]"),
    (["--gae-lambda", "-0.1"], "--gae-lambda must be in [0, 1]"),
    (["--ent-coef", "-1"], "--ent-coef must be in [0, inf]"),
    (["--update-epochs", "0"], "--update-epochs must be positive"),
    (["--device", "tpu"], "--device tpu is not available"),
    (["--run-dir", "afile"], "is a file"),
    (["--run-dir", "afile/sub"], "--run-dir afile/sub cannot be created or written"),
    (["--run-dir", "/proc/1/nope"], "--run-dir /proc/1/nope cannot be created or written"),
    (["--run-dir", "oldrun"], "already holds a run: continue it with --resume oldrun/checkpoint.pt"),
    (["--env-id", "NoSuchEnv-v0"], "unknown env id"),
    (["--env-id", "{wrong_action_space_env}"], "action space"),
    (["--num-steps", "100", "--minibatch-size", "64"], "does not divide"),
    (["--total-timesteps", "0"], "must be positive"),
    (["--total-timesteps", "-5"], "must be positive"),
    (["--num-envs", "0"], "must be positive"),
    (["--resume", "missing.pt"], "does not exist"),
    (["--eval-checkpoint", "corrupt.pt"], "corrupt"),
    (["--resume", "notacheckpoint.pt"], "not a checkpoint"),
    (["--anneal-logstd", "nan", "-1.6"], "--anneal-logstd must be two finite numbers"),
    (["--anneal-logstd", "-0.7", "inf"], "--anneal-logstd must be two finite numbers"),
    (["--lr-target-kl", "0", "--no-anneal-lr"], "--lr-target-kl must be positive"),
    (["--lr-target-kl", "nan", "--no-anneal-lr"], "--lr-target-kl must be a finite number"),
    (["--lr-target-kl", "0.01"], "--lr-target-kl adapts the learning rate to the KL: add --no-anneal-lr"),
]


# A few of them through a new interpreter, as a user's shell runs the script; every one through main() in this
# process, which is the same code from the parsing of argv on, without a second or two of imports per case.
IN_A_SUBPROCESS = {"--learning-rate must be a finite number, got nan", "unknown env id", "is a file"}


def skip_flags_it_lacks(script, args):
    """A bad value of a flag the script does not have is not its case: ppo_rlhf.py has no env or env steps."""
    flags = {"--" + f.name.replace("_", "-") for f in dataclasses.fields(load_script(script).Args)}
    missing = [a for a in args if a.startswith("--") and a not in flags]
    if missing:
        pytest.skip(f"{script} has no {', '.join(missing)}")


def bad_input_files(tmp_path):
    (tmp_path / "corrupt.pt").write_bytes(b"\x80\x02this is not a checkpoint")
    (tmp_path / "afile").write_text("")
    (tmp_path / "oldrun").mkdir()
    (tmp_path / "oldrun" / "events.out.tfevents.1.host").write_bytes(b"")
    torch.save({"some": "dict"}, tmp_path / "notacheckpoint.pt")


@pytest.mark.parametrize("args,message", BAD_INPUTS, ids=[m for _, m in BAD_INPUTS])
def test_bad_input_is_one_clear_line_before_training(script, tmp_path, args, message, monkeypatch, capsys):
    skip_flags_it_lacks(script, args)
    bad_input_files(tmp_path)
    args = [a.format(**TINY[script]) for a in args]
    module = load_script(script)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [script, *args])
    monkeypatch.setattr(module, "train", lambda *args, **kwargs: pytest.fail("training started"))
    monkeypatch.setattr(module, "evaluate", lambda args: pytest.fail("evaluation started"), raising=False)
    with pytest.raises(SystemExit) as stopped:
        module.main()
    err = capsys.readouterr().err
    assert stopped.value.code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and message in lines[0], err
    assert not (tmp_path / "runs").exists(), "training started"


@pytest.mark.parametrize(
    "args,message", [case for case in BAD_INPUTS if case[1] in IN_A_SUBPROCESS], ids=sorted(IN_A_SUBPROCESS)
)
def test_bad_input_from_the_shell_is_one_line_and_exit_2(script, tmp_path, args, message):
    skip_flags_it_lacks(script, args)
    bad_input_files(tmp_path)
    proc = run_cli(script, *[a.format(**TINY[script]) for a in args], cwd=tmp_path, check=False)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and message in lines[0], proc.stderr
    assert not (tmp_path / "runs").exists(), "training started"


@pytest.mark.parametrize(
    "script", [s for s in SCRIPTS if s != "ppo_atari.py"]
)  # Atari's: test_atari.py, whole games in colour
def test_training_records_video_of_the_first_env(script, tmp_path):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    import imageio.v3 as iio

    run_dir, _ = train_tiny(script, tmp_path, "run", "--capture-video")
    videos = sorted((run_dir / "videos").rglob("*.mp4"))
    assert videos, list(run_dir.rglob("*"))
    frames = np.stack(list(iio.imiter(videos[0])))
    assert frames.shape[0] > 1 and frames.std() > 5


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s != "ppo_atari.py"])
def test_atari_id_points_to_the_atari_script(script, tmp_path):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    proc = run_cli(script, "--env-id", "ALE/Breakout-v5", cwd=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Use ppo_atari.py for Atari games" in lines[0], proc.stderr


@pytest.mark.parametrize("script", [s for s in SCRIPTS if s != "ppo_atari.py"])
def test_mujoco_scripts_check_their_input_without_ale_py(script, tmp_path):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    # A MuJoCo script copied into a project without ale-py still gives its one-line errors (sys.modules[name] = None
    # makes `import name` fail as if the package were not installed).
    code = (
        f"import runpy, sys; sys.modules['ale_py'] = None; sys.argv = [{script!r}, '--env-id', 'NoSuchEnv-v0'];"
        f" runpy.run_path({str(ROOT / script)!r}, run_name='__main__')"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "unknown env id" in lines[0], proc.stderr


def test_divergence_stops_with_one_line_and_keeps_the_last_finite_checkpoint(script, tmp_path, tiny_run, monkeypatch):
    needs_env(script)  # tests/test_rlhf.py has ppo_rlhf.py's own smoke, resume and divergence checks
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run(script)[0], run_dir)
    path = run_dir / "checkpoint.pt"
    checkpoint = torch.load(path, weights_only=True)
    # Roll back one iteration and continue with a learning rate at which any of these networks diverges.
    checkpoint["args"]["learning_rate"] = 1000.0
    checkpoint["iteration"] -= 1
    checkpoint["global_step"] -= checkpoint["global_step"] // (checkpoint["iteration"] + 1)
    torch.save(checkpoint, path)
    before = path.read_bytes()
    proc = run_cli(script, "--resume", path, cwd=tmp_path, check=False)
    assert proc.returncode == 1, (proc.stdout, proc.stderr)
    lines = [line for line in proc.stderr.strip().splitlines() if "Profiler" not in line]
    assert len(lines) == 1 and "not finite after iteration" in lines[0] and "smaller --learning-rate" in lines[0], (
        proc.stderr
    )
    assert path.read_bytes() == before, "the last finite checkpoint stays on disk"
    assert all(
        torch.isfinite(v).all()
        for v in torch.load(path, weights_only=True)["agent"].values()
        if isinstance(v, torch.Tensor)
    )
    # The advice is one the script takes: a new run with a smaller learning rate, where --resume would refuse it.
    advice = re.search(r"start a new run with a smaller (--[a-z-]+)", lines[0])
    assert advice, lines[0]
    smaller = [advice[1], "0.0001"]
    new_run = ["--env-id", TINY[script]["env_id"], *TINY[script]["tiny"], *smaller, "--run-dir", tmp_path / "anew"]
    module = load_script(script)
    assert call_main(module, [*new_run, *ONE_THREAD], monkeypatch).learning_rate == 0.0001  # training starts
    assert call_main(module, ["--resume", path, *smaller, *ONE_THREAD], monkeypatch) == 2


@pytest.mark.parametrize("script", ["ppo_continuous.py"])
def test_compile_runs_the_same_algorithm(script, tmp_path, monkeypatch):
    # --compile changes how the update runs, not what it computes: the same losses, to float tolerance.
    monkeypatch.setenv(
        "TORCH_LOGS", "graph_code"
    )  # torch prints each graph it compiles, to tell that it compiled at all
    eager, eager_proc = train_tiny(script, tmp_path, "eager", "--seed", "5")
    compiled, compiled_proc = train_tiny(script, tmp_path, "compiled", "--seed", "5", "--compile")
    assert "TRACED GRAPH" not in eager_proc.stderr and "TRACED GRAPH" in compiled_proc.stderr
    a, b = tb_scalars(eager), tb_scalars(compiled)
    assert a["charts/episodic_return"][:3] == b["charts/episodic_return"][:3], (
        "the first rollout samples the same actions"
    )
    for tag in ["losses/policy_loss", "losses/value_loss", "losses/approx_kl"]:
        np.testing.assert_allclose([v for _, v in a[tag]], [v for _, v in b[tag]], rtol=1e-3, atol=1e-5, err_msg=tag)


def test_video_follows_the_walker(tmp_path):
    # A Hopper carried 40 m down its track while it is filmed: in the last frame of the video, the tracking
    # camera still shows it; a fixed camera, as a control, shows empty floor. The body is Hopper's brownish
    # (0.8, 0.6, 0.4); the floor and the sky are blue and grey.
    import os

    import gymnasium as gym
    import imageio.v3 as iio

    os.environ.setdefault("MUJOCO_GL", "egl")
    module = load_script("ppo_continuous.py")

    def last_frame_body_pixels(env, video_dir):
        env.reset(seed=0)
        qpos, qvel = env.unwrapped.init_qpos.copy(), env.unwrapped.init_qvel.copy()
        for t in range(40):
            qpos[0] = float(t)  # 1 m per step: far out of a fixed camera's view
            env.unwrapped.set_state(qpos, qvel)
            env.step(np.zeros(3))
        env.close()
        frames = np.stack(list(iio.imiter(next(video_dir.glob("*.mp4"))))).astype(int)
        r, g, b = frames[..., 0], frames[..., 1], frames[..., 2]
        body = ((r > g + 20) & (g > b + 10)).sum(axis=(1, 2))
        assert len(frames) > 30 and body[0] > 2000, "the robot is in the first frame"
        return int(body[-1])

    tracked = module.make_env("Hopper-v5", capture_video=True, video_dir=str(tmp_path / "tracked"))
    fixed = gym.wrappers.RecordVideo(
        gym.make("Hopper-v5", render_mode="rgb_array", camera_id=-1), str(tmp_path / "fixed")
    )
    assert last_frame_body_pixels(tracked, tmp_path / "tracked") > 2000
    assert last_frame_body_pixels(fixed, tmp_path / "fixed") < 30, "the check tells a visible robot from empty floor"


@pytest.mark.parametrize("name", scripts_with("make_env"))
def test_filming_with_the_tracking_camera_leaves_no_other_env_open(name, tmp_path, monkeypatch):
    # To find Hopper's tracking camera, make_env makes an env, reads its cameras, then makes the one it films.
    import gymnasium as gym

    made, closed = [], []
    real_make = gym.make

    def make(*args, **kwargs):
        env = real_make(*args, **kwargs)
        real_close = env.close
        env.close = lambda: (closed.append(env), real_close())
        made.append(env)
        return env

    monkeypatch.setattr(gym, "make", make)
    filmed = load_script(name).make_env("Hopper-v5", capture_video=True, video_dir=str(tmp_path))
    assert len(made) == 2 and closed == [made[0]], "the first env is closed, the filmed one is not"
    filmed.close()


@pytest.mark.parametrize("script", ["ppo_continuous.py", "ppo_kl_penalty.py"])
def test_the_progress_line_prints_a_dash_until_an_episode_ends(script, tmp_path):
    """Pendulum's episodes last 200 steps, so after the first 64 no episode has ended: the first progress
    line says `return -`, not nan; the last, after 256 steps, a number."""
    flags = ["--env-id", "Pendulum-v1", "--num-steps", "64", "--minibatch-size", "64", "--update-epochs", "1"]
    out = run_cli(script, *flags, "--total-timesteps", "256", "--run-dir", "run", cwd=tmp_path).stdout
    returns = re.findall(r"\| return (\S+) \|", out)
    assert returns[0] == "-" and "nan" not in out
    assert float(returns[-1]) < 0  # Pendulum pays only costs
