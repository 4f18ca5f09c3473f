"""--track, as CleanRL's: a Weights & Biases run that mirrors the TensorBoard scalars (and keeps the videos), tested
offline; without --track nothing of wandb is imported; without a login or a network, the run goes on offline."""

import os
import subprocess
import sys

import pytest
from conftest import ONE_THREAD, ROOT, SCRIPTS, TINY


def wandb_env(home, **more):
    """A user with no W&B login (a fresh HOME) and none of this machine's W&B settings."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")}
    return {**env, "HOME": str(home), "PYTHONUNBUFFERED": "1", **more}


def run(script, *args, cwd, env, timeout=300):
    """The script's real command line on its tiny budget, with --track; the CompletedProcess."""
    cfg = TINY[script]
    env_flag = ["--env-id", cfg["env_id"]] if "env_id" in cfg else []
    cmd = [sys.executable, str(ROOT / script), *env_flag, *cfg["tiny"], *map(str, args), *ONE_THREAD]
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def offline_runs(cwd, name):
    """The offline W&B runs that a --track run named `name` left in cwd/wandb."""
    return sorted((cwd / "wandb").glob(f"offline-run-*-{name}"))


@pytest.mark.parametrize("script", SCRIPTS)
def test_track_offline_leaves_a_run_with_the_scalars(script, tmp_path):
    video = ["--capture-video"] if script == "ppo_continuous.py" else []
    run(script, "--track", "--run-dir", "r1", *video, cwd=tmp_path, env=wandb_env(tmp_path, WANDB_MODE="offline"))
    (offline,) = offline_runs(tmp_path, "r1")
    log = (offline / "run-r1.wandb").read_bytes()  # the run's records, which `wandb sync` uploads
    scalar = b"rlhf/" if script == "ppo_rlhf.py" else b"charts/episodic_return"
    assert scalar in log and b"losses/policy_loss" in log
    assert any((tmp_path / "r1").glob("events.out.tfevents.*")), "the TensorBoard logs are kept as without --track"
    if video:  # the videos filmed in training go with the run
        filmed = {p.name for p in (tmp_path / "r1" / "videos").glob("*.mp4")}
        assert filmed and {p.name for p in (offline / "files" / "videos").glob("*.mp4")} == filmed


def test_resume_with_track_continues_the_same_wandb_run(tmp_path):
    env = wandb_env(tmp_path, WANDB_MODE="offline")
    script = "ppo_continuous.py"
    run(script, "--track", "--run-dir", "r1", cwd=tmp_path, env=env)
    run(script, "--track", "--resume", "r1/checkpoint.pt", "--save-every", "3", cwd=tmp_path, env=env)
    assert len(offline_runs(tmp_path, "r1")) == 2, "two processes, one W&B run id: the run directory's name"


def test_without_track_nothing_of_wandb_is_imported(tmp_path):
    cfg = TINY["ppo_continuous.py"]
    argv = [str(ROOT / "ppo_continuous.py"), "--env-id", cfg["env_id"], *cfg["tiny"], "--run-dir", "r1", *ONE_THREAD]
    code = (
        f"import runpy, sys; sys.argv = {argv!r}; runpy.run_path(sys.argv[0], run_name='__main__');"
        " print('wandb' in sys.modules)"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "False"


@pytest.mark.parametrize("case", ["no login", "no network"])
def test_track_without_login_or_network_goes_on_offline(case, tmp_path):
    """No API key: W&B refuses at once. A key but no server that answers (a closed port on this machine): W&B gives up
    after its init timeout, shortened here. Either way the run trains, keeps its TensorBoard logs, and logs offline."""
    more = {} if case == "no login" else {"WANDB_API_KEY": "a" * 40, "WANDB_BASE_URL": "http://127.0.0.1:9"}
    env = wandb_env(tmp_path, WANDB_INIT_TIMEOUT="5", **more)
    proc = run("ppo_continuous.py", "--track", "--run-dir", "r1", cwd=tmp_path, env=env)
    assert "logging offline instead, for `wandb sync` to upload" in proc.stderr
    assert (tmp_path / "r1" / "checkpoint.pt").exists() and any((tmp_path / "r1").glob("events.out.tfevents.*"))
    (offline,) = offline_runs(tmp_path, "r1")
    assert b"charts/episodic_return" in (offline / "run-r1.wandb").read_bytes()
