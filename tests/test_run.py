"""benchmarks/run.py and benchmarks/results.py: the runner never loses or repeats work, rejects a bad grid before it
starts anything, runs the same on its Ray backend, and leaves each finished run in the results folder with the series
it logged."""

import contextlib
import dataclasses
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from conftest import ROOT, fake_run, signal_at_checkpoint

sys.path.insert(0, str(ROOT / "benchmarks"))
import report  # noqa: E402

import run  # noqa: E402
from common import load_script  # noqa: E402
from results import BEST_OF_N, RLHF_STATS, UPDATE_STATS, read_csv, write_csv  # noqa: E402
from suites import MUJOCO, SUITES, Suite  # noqa: E402

# One iteration of ppo_continuous.py's default batch is 2048 steps; InvertedPendulum is the cheapest env.
TINY_GRID = ["--envs", "InvertedPendulum", "--seeds", "1"]


def runner(*args, tmp_path, check=True, timeout=300):
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "run.py"),
            *args,
            "--results-dir",
            str(tmp_path / "results"),
            "--runs-dir",
            str(tmp_path / "runs"),
            "--status-every",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"run.py {' '.join(args)} exited {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.mark.parametrize(
    "args, message",
    [
        (["nosuchsuite"], "unknown suite 'nosuchsuite'"),
        (["table1", "--variants", "clip0.25"], "has no variant 'clip0.25'"),
        (["mujoco", "--envs", "Hoppper-v5"], "unknown env id 'Hoppper-v5'"),
        (["mujoco", "--envs", "CartPole-v1"], "needs a Box action space"),
        (["mujoco", "--workers", "0"], "--workers must be positive"),
    ],
)
def test_runner_rejects_a_bad_grid_before_starting(tmp_path, args, message):
    proc = runner(*args, tmp_path=tmp_path, check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "runs").exists(), "nothing may start"


def test_check_grid_rejects_a_flag_the_script_lacks(tmp_path):
    job = run.make_grid("mujoco", envs=["Hopper"], seeds=[1], results_root=tmp_path, runs_root=tmp_path)[0]
    job.flags = ["--kl-target", "0.01"]  # ppo_kl_penalty.py's flag, not ppo_continuous.py's
    with pytest.raises(ValueError, match="does not accept the flags --kl-target 0.01"):
        run.check_grid([job])


@pytest.mark.parametrize("suite", list(SUITES))
def test_every_suite_is_a_valid_grid(suite):
    """Each variant's flags parse with its script's own parser, and each env passes its checks."""
    run.check_grid(run.make_grid(suite))


def test_a_variant_runs_only_on_the_envs_and_seeds_its_suite_gives_it(monkeypatch):
    """Suite.only limits a variant to some envs and seeds; the other variants run on the whole grid. A short name
    ('Swimmer') stands for the suite's env."""
    tiny = Suite(
        {"a": ("ppo_continuous.py", []), "b": ("ppo_continuous.py", ["--gamma", "0.999"])},
        ["Hopper-v5", "Swimmer-v5"],
        [1, 2],
        2048,
        only={"b": (["Swimmer-v5"], [2])},
    )
    monkeypatch.setitem(SUITES, "tiny", tiny)
    jobs = {(job.variant, job.env_id, job.seed) for job in run.make_grid("tiny")}
    assert jobs == {
        ("a", "Hopper-v5", 1),
        ("a", "Hopper-v5", 2),
        ("a", "Swimmer-v5", 1),
        ("a", "Swimmer-v5", 2),
        ("b", "Swimmer-v5", 2),
    }
    assert {(j.variant, j.env_id, j.seed) for j in run.make_grid("tiny", envs=["Swimmer"], seeds=[2])} == {
        ("a", "Swimmer-v5", 2),
        ("b", "Swimmer-v5", 2),
    }


def test_atari_suite_is_three_games_three_seeds_and_the_arms_of_issue_30():
    runs = {(job.variant, job.env_id.split("NoFrameskip")[0], job.seed) for job in run.make_grid("atari")}
    assert {(e, s) for v, e, s in runs if v == "ppo"} == {
        (e, s) for e in ("Pong", "Breakout", "BeamRider") for s in (1, 2, 3)
    }
    for arm in ("vf0.5", "e4", "zoo", "sb3"):  # where we trail the peer: Pong and Breakout, 3 seeds each
        assert {(e, s) for v, e, s in runs if v == arm} == {(e, s) for e in ("Pong", "Breakout") for s in (1, 2, 3)}
    assert {(e, s) for v, e, s in runs if v == "novclip"} == {("Pong", s) for s in (1, 2, 3)}
    assert {job.total_timesteps for job in run.make_grid("atari")} == {1_000_000}
    # Each arm is ppo_atari.py at its defaults but for the settings the arm names, as the script parses its flags.
    import tyro

    parsed = {}
    for name, (script, flags) in SUITES["atari"].variants.items():
        if script == "ppo_atari.py":
            args = tyro.cli(load_script(script).Args, args=flags)
            parsed[name] = (args.vf_coef, args.update_epochs, args.clip_vloss)
    default = load_script("ppo_atari.py").Args()
    vf, epochs, clip = default.vf_coef, default.update_epochs, default.clip_vloss
    assert (vf, epochs, clip) == (1.0, 3, True), "Table 5's c1 and K, and baselines' value clipping"
    assert parsed == {
        "ppo": (vf, epochs, clip),
        "vf0.5": (0.5, epochs, clip),
        "e4": (vf, 4, clip),
        "novclip": (vf, epochs, False),
        "zoo": (0.5, 4, False),
    }


def test_table1_rows_are_the_papers():
    import tyro

    variants = SUITES["table1"].variants
    parsed = {
        name: (script, tyro.cli(load_script(script).Args, args=flags)) for name, (script, flags) in variants.items()
    }
    assert parsed["no-clip"][1].init_beta == 0 and not parsed["no-clip"][1].adaptive_beta
    assert [parsed[f"clip{e}"][1].clip_coef for e in ("0.1", "0.2", "0.3")] == [0.1, 0.2, 0.3]
    for d in ("0.003", "0.01", "0.03"):
        args = parsed[f"kl{d}"][1]
        assert (
            parsed[f"kl{d}"][0] == "ppo_kl_penalty.py"
            and args.adaptive_beta
            and args.kl_target == float(d)
            and args.init_beta == 1
        )
    for b in ("0.3", "1", "3", "10"):
        args = parsed[f"beta{b}"][1]
        assert not args.adaptive_beta and args.init_beta == float(b)
    assert set(SUITES["table1"].envs) == set(MUJOCO) and len(MUJOCO) == 7


def test_runner_finishes_skips_and_shares_identical_runs(tmp_path):
    first = runner("mujoco", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    out = tmp_path / "results" / run.results_folder("mujoco", 4096) / "InvertedPendulum-v5__clip0.2__seed1.csv"
    assert out.exists(), first.stdout
    meta, rows = read_csv(out)
    for key in ("command", "commit", "versions", "machine", "wall_time_s"):
        assert meta[key], key
    assert meta["command"].startswith("python ppo_continuous.py ") and "--total-timesteps 4096" in meta["command"]
    assert int(meta["global_step"]) == 4096 and "torch" in meta["versions"]
    steps = [step for step, _, _ in rows]
    assert len(rows) > 10 and steps == sorted(steps) and steps[-1] <= 4096
    assert all(length > 0 for _, _, length in rows)
    updates = (
        (out.parent / "updates" / out.name).read_text().splitlines()
    )  # the update's statistics, one row per iteration
    assert updates[0] == "global_step,entropy,approx_kl,clipfrac,explained_variance,value_loss"
    assert [int(line.split(",")[0]) for line in updates[1:]] == [2048, 4096]
    assert all(math.isfinite(float(x)) for line in updates[1:] for x in line.split(","))
    content = out.read_bytes()

    again = runner("mujoco", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    assert "1/1 runs finished, 0 to run" in again.stdout and "start" not in again.stdout
    assert out.read_bytes() == content
    attempts = (
        (
            tmp_path
            / "runs"
            / run.results_folder("mujoco", 4096)
            / "InvertedPendulum-v5__clip0.2__seed1"
            / "attempts.txt"
        )
        .read_text()
        .splitlines()
    )
    assert len(attempts) == 1, "a finished run is not run again"

    # table1's clip0.2 row is the same run: copied, not run again.
    shared = runner("table1", "--variants", "clip0.2", *TINY_GRID, "--total-timesteps", "4096", tmp_path=tmp_path)
    assert "copied" in shared.stdout
    assert (
        tmp_path / "results" / run.results_folder("table1", 4096) / "InvertedPendulum-v5__clip0.2__seed1.csv"
    ).read_bytes() == content
    assert (tmp_path / "results" / run.results_folder("table1", 4096) / "updates" / out.name).read_text() == "\n".join(
        updates
    ) + "\n"
    assert not (tmp_path / "runs" / run.results_folder("table1", 4096)).exists()


def test_finish_keeps_what_the_run_logged_and_what_its_script_adds(tmp_path):
    """finish() writes the series a run logged (here beta and the update's statistics, and no rlhf/* scalars, so no
    rlhf series or samples) and the header lines and packages that its script declares, whatever its name."""
    from torch.utils.tensorboard import SummaryWriter

    script = tmp_path / "peer.py"
    script.write_text(
        'RESULTS_PACKAGES = ("pytest",)\n\n\n'
        "def results_header(flags, env_id):\n"
        '    return [("hyperparameters", f"{env_id} with {flags[1]}")]\n'
    )
    job = run.Job("tiny", "a", str(script), ["--x", "7"], "Hopper-v5", 1, 256, tmp_path / "results", tmp_path / "runs")
    job.run_dir.mkdir(parents=True)
    with SummaryWriter(job.run_dir) as writer:
        for step, episodic_return in ((100, 1.0), (200, 3.0)):
            writer.add_scalar("charts/episodic_return", episodic_return, step)
            writer.add_scalar("charts/episodic_length", 10, step)
        for step, beta in ((128, 1.0), (256, 0.5)):
            writer.add_scalar("losses/beta", beta, step)
            writer.add_scalar("losses/kl", 0.25, step)
            for name in UPDATE_STATS:
                writer.add_scalar(f"losses/{name}", 0.5, step)
    torch.save({"global_step": 256}, job.checkpoint)
    (job.run_dir / "attempts.txt").write_text("2026-01-01T00:00:00\tabc1234\t30\t0\tstart\n")
    assert run.finish(job) == 2.0, "the mean of the last 100 episodes' returns"
    meta, rows = read_csv(job.csv)
    assert rows == [(100, 1.0, 10), (200, 3.0, 10)] and meta["global_step"] == "256"
    assert meta["hyperparameters"] == "Hopper-v5 with 7" and ", pytest " in meta["versions"]
    assert meta["commit"] == "abc1234" and meta["wall_time_s"] == "30" and meta["attempts"] == "1"
    assert meta["beta_range"] == "0.5..1 (first 90% of updates: 1..1)"
    beta = (job.results_dir / "beta" / f"{job.name}.csv").read_text()
    assert beta == "global_step,beta,kl\n128,1,0.25\n256,0.5,0.25\n"
    updates = (job.results_dir / "updates" / f"{job.name}.csv").read_text().splitlines()
    assert updates == ["global_step," + ",".join(UPDATE_STATS), "128" + ",0.5" * 5, "256" + ",0.5" * 5]
    assert not (job.results_dir / "rlhf").exists() and not (job.results_dir / "samples").exists()


def test_a_shared_kl_run_brings_its_beta_series(tmp_path):
    # beta_collapse's kl0.01 runs are table1's: the copy must carry the beta series that the beta plot reads.
    source = tmp_path / "results" / run.results_folder("table1", 4096)
    fake_run(source, "Hopper-v5", "kl0.01", 1, 100.0, steps=4096)
    (source / "beta").mkdir()
    (source / "beta" / "Hopper-v5__kl0.01__seed1.csv").write_text("global_step,beta,kl\n2048,1,0.01\n4096,0.5,0.001\n")
    shared = runner(
        "beta_collapse", "--variants", "kl0.01", "--seeds", "1", "--total-timesteps", "4096", tmp_path=tmp_path
    )
    assert "copied" in shared.stdout and "start" not in shared.stdout
    copy = tmp_path / "results" / run.results_folder("beta_collapse", 4096)
    assert (copy / "Hopper-v5__kl0.01__seed1.csv").read_bytes() == (
        source / "Hopper-v5__kl0.01__seed1.csv"
    ).read_bytes()
    assert (copy / "beta" / "Hopper-v5__kl0.01__seed1.csv").read_text() == (
        source / "beta" / "Hopper-v5__kl0.01__seed1.csv"
    ).read_text()


def tiny_sweep(tmp_path, total, *extra, status_every="1"):
    """The runner's command for one KL run of `total` steps that saves after each iteration, and its run's folder."""
    cmd = [
        sys.executable,
        str(ROOT / "benchmarks" / "run.py"),
        "table1",
        "--variants",
        "kl0.01",
        *TINY_GRID,
        "--total-timesteps",
        str(total),
        "--save-every",
        "1",
        "--results-dir",
        str(tmp_path / "results"),
        "--runs-dir",
        str(tmp_path / "runs"),
        "--status-every",
        status_every,
        *extra,
    ]
    return cmd, tmp_path / "runs" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1"


def interrupt_at_first_checkpoint(tmp_path, total, *extra):
    """Start a sweep of one KL run of `total` steps, SIGTERM the runner once the run has saved a checkpoint,
    and check that it stopped there. Returns the runner's command and the checkpoint's step."""
    cmd, run_dir = tiny_sweep(tmp_path, total, *extra)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGTERM, wait=180)
    assert proc.returncode == 130, (out, err)
    assert "its checkpoint is kept" in out and "Traceback" not in err
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert 0 < saved["global_step"] < total
    return cmd, saved["global_step"], run_dir


def test_runner_resumes_an_interrupted_run(tmp_path):
    total = 6 * 2048  # six iterations, with a checkpoint after each
    cmd, saved_step, run_dir = interrupt_at_first_checkpoint(tmp_path, total)
    csv_path = tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    assert not csv_path.exists(), "an unfinished run has no CSV"

    resumed = subprocess.run(cmd, capture_output=True, text=True, timeout=300)  # the same command again
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert "resume InvertedPendulum-v5__kl0.01__seed1" in resumed.stdout
    assert f"at step {saved_step:,}" in (run_dir / "log.txt").read_text()
    meta, rows = read_csv(csv_path)
    assert int(meta["global_step"]) == total and int(meta["attempts"]) == 2
    assert meta["command"].startswith("python ppo_kl_penalty.py ") and "beta_range" in meta
    beta = (csv_path.parent / "beta" / csv_path.name).read_text().splitlines()
    assert beta[0] == "global_step,beta,kl" and len(beta) - 1 == total // 2048, "beta after each of the run's updates"
    assert [int(line.split(",")[0]) for line in beta[1:]] == list(range(2048, total + 1, 2048))
    updates = (csv_path.parent / "updates" / csv_path.name).read_text().splitlines()
    assert [int(line.split(",")[0]) for line in updates[1:]] == list(range(2048, total + 1, 2048)), (
        "one row per update, across the resume"
    )
    steps = [step for step, _, _ in rows]
    assert steps == sorted(steps), "one curve, without a fold at the resume"
    attempts = [line.split("\t") for line in (run_dir / "attempts.txt").read_text().splitlines()]
    assert [a[4] for a in attempts] == ["start", "resume"] and [a[3] for a in attempts] == ["130", "0"]


def test_a_run_another_runner_finished_meanwhile_is_skipped(tmp_path):
    """Two runners may share a grid (one per core, say): a run whose CSV appeared after this runner listed it is not
    resumed and written again."""
    total = 2048
    folder = run.results_folder("mujoco", total)
    first_dir = tmp_path / "runs" / folder / "InvertedPendulum-v5__clip0.2__seed1"
    second_csv = tmp_path / "results" / folder / "InvertedPendulum-v5__clip0.2__seed2.csv"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "run.py"), "mujoco", "--envs", "InvertedPendulum"]
    cmd += ["--seeds", "1", "2", "--workers", "1", "--total-timesteps", str(total)]
    cmd += ["--results-dir", str(tmp_path / "results"), "--runs-dir", str(tmp_path / "runs")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for _ in range(600):  # the first run has started: the runner has listed both
            if (first_dir / "pid").exists() or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the first run ended before the test could finish the second"
        write_csv(second_csv, [("note", "finished by another runner")], [(1, 1.0, 1)])
        out, err = proc.communicate(timeout=300)
    finally:
        with contextlib.suppress(OSError):
            proc.kill()
    assert proc.returncode == 0, out + err
    assert "skip   InvertedPendulum-v5__clip0.2__seed2: another runner finished it" in out
    assert read_csv(second_csv)[0] == {"note": "finished by another runner"}, "not written again"
    assert not (tmp_path / "runs" / folder / "InvertedPendulum-v5__clip0.2__seed2").exists()


def test_a_runner_killed_outright_loses_no_attempt(tmp_path):
    """SIGKILL (or a machine that shuts down) gives the runner no chance to log the attempt; the next runner logs
    it from the file the killed one kept current, so the run's wall time and commits count it."""
    total = 6 * 2048
    cmd, run_dir = tiny_sweep(tmp_path, total, status_every="0.2")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGKILL, wait=180)
    finally:
        with contextlib.suppress(OSError, ValueError):  # its run dies with it, as on a shutdown
            os.kill(int((run_dir / "pid").read_text()), signal.SIGKILL)
    noted = (run_dir / "attempt.txt").read_text().split("\t")
    assert noted[3] == "running" and noted[4].strip() == "start" and int(noted[2]) >= 1
    assert not (run_dir / "attempts.txt").exists(), "the killed runner logged nothing"
    runner("table1", "--variants", "kl0.01", *TINY_GRID, "--total-timesteps", str(total), tmp_path=tmp_path)
    attempts = [line.split("\t") for line in (run_dir / "attempts.txt").read_text().splitlines()]
    assert [a[3:] for a in attempts] == [["killed", "start"], ["0", "resume"]]
    assert int(attempts[0][2]) >= int(noted[2]) and not (run_dir / "attempt.txt").exists()
    csv_path = tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    meta, _ = read_csv(csv_path)
    assert int(meta["attempts"]) == 2 and int(meta["global_step"]) == total
    assert int(meta["wall_time_s"]) == sum(int(a[2]) for a in attempts)


# ---------------------------------------------------------------- the Ray backend, on a local Ray instance


def test_ray_backend_makes_the_same_results_as_the_local_one_and_skips_them_after(tmp_path):
    pytest.importorskip("ray")  # benchmarks/requirements.txt; .ci/run installs it
    grid = ["table1", "--variants", "kl0.01", *TINY_GRID, "--total-timesteps", "2048"]
    runner(*grid, tmp_path=tmp_path / "local")
    first = runner(*grid, "--backend", "ray", tmp_path=tmp_path / "ray")
    assert "done   InvertedPendulum-v5__kl0.01__seed1" in first.stdout and "1/1 runs finished" in first.stdout
    files = {p.relative_to(tmp_path / "ray" / "results") for p in (tmp_path / "ray" / "results").rglob("*.csv")}
    assert files == {
        p.relative_to(tmp_path / "local" / "results") for p in (tmp_path / "local" / "results").rglob("*.csv")
    }
    for path in files:  # the same run, to the episode and to every value of its series: only when, and how long, differ
        local, ray = (tmp_path / backend / "results" / path for backend in ("local", "ray"))
        if path.parent.name in ("beta", "updates"):
            assert local.read_text() == ray.read_text()
            continue
        (meta_l, rows_l), (meta_r, rows_r) = read_csv(local), read_csv(ray)
        assert rows_l == rows_r and meta_l.keys() == meta_r.keys()
        assert meta_l["command"].replace(str(tmp_path / "local"), "") == meta_r["command"].replace(
            str(tmp_path / "ray"), ""
        )
    again = runner(*grid, "--backend", "ray", tmp_path=tmp_path / "ray")
    assert "1/1 runs finished, 0 to run" in again.stdout and "start" not in again.stdout


def test_ray_backend_stops_every_run_at_a_checkpoint_and_resumes(tmp_path):
    pytest.importorskip("ray")
    total = 6 * 2048
    cmd, _, _ = interrupt_at_first_checkpoint(tmp_path, total, "--backend", "ray")
    resumed = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0 and "resume InvertedPendulum-v5__kl0.01__seed1" in resumed.stdout, (
        resumed.stdout + resumed.stderr
    )
    meta, _ = read_csv(
        tmp_path / "results" / run.results_folder("table1", total) / "InvertedPendulum-v5__kl0.01__seed1.csv"
    )
    assert int(meta["global_step"]) == total and int(meta["attempts"]) == 2


@pytest.mark.parametrize(
    "args, message",
    [
        (["table1", "--variants", "clip0.25", "--backend", "ray"], "has no variant 'clip0.25'"),
        (
            ["table1", *TINY_GRID, "--backend", "ray", "--ray-address", "127.0.0.1:1"],
            "no Ray cluster answers at --ray-address 127.0.0.1:1",
        ),
    ],
)
def test_ray_backend_rejects_a_bad_grid_or_address_in_one_line(tmp_path, args, message):
    proc = runner(*args, tmp_path=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode != 0 and len(lines) == 1 and message in lines[0], proc.stderr
    assert not (tmp_path / "runs").exists(), "nothing may start"


def test_progress_reads_the_last_step_or_rlhf_iteration_a_run_printed(tmp_path):
    job = run.make_grid("rlhf-long", ["beta0"], seeds=[1], results_root=tmp_path, runs_root=tmp_path)[0]
    assert run.last_step(job) == 0, "no log yet"
    job.run_dir.mkdir(parents=True)
    log = "stage 2, reward model: step 212/212 | loss 0.2\nstage 3, PPO: iteration 400/1,600 | score +1.00\n"
    (job.run_dir / "log.txt").write_text(log)
    assert run.last_step(job) == job.total_timesteps // 4
    (job.run_dir / "log.txt").write_text("step 12,345/1,000,000 | SPS 900\n")  # the gym scripts' lines
    assert run.last_step(job) == 12_345
    # A resume after a failed attempt: the attempt's traceback follows the last step, as two ranks' did (8 KB).
    traceback = "".join(
        f'[rank{r}]:   File "ppo_continuous.py", line {i}, in train\n' for r in (0, 1) for i in range(100)
    )
    (job.run_dir / "log.txt").write_text("step 36,241,408/50,003,968 | SPS 4219\n" + traceback)
    assert len(traceback) > 8000 and run.last_step(job) == 36_241_408


def test_a_long_run_keeps_the_first_checkpoint_at_or_past_each_mark_of_its_suite(tmp_path, monkeypatch):
    """roboschool-body's 100M runs are measured at 50M too: the runner copies aside the first checkpoint a run saves at
    or past the mark, and no later one replaces it."""
    assert run.SUITES["roboschool-body"].keep_checkpoints == {"50M": 50_003_968}
    monkeypatch.setitem(run.SUITES, "table1", dataclasses.replace(run.SUITES["table1"], keep_checkpoints={"4k": 4096}))
    (job,) = run.make_grid("table1", ["kl0.01"], ["InvertedPendulum"], [1], 4 * 2048, tmp_path, tmp_path)
    job.run_dir.mkdir(parents=True)
    kept, seen = job.run_dir / "checkpoint_4k.pt", {}
    for step, mtime in [(2048, 1), (4096, 2), (6144, 3), (8192, 4)]:
        torch.save({"global_step": step}, job.checkpoint)
        os.utime(job.checkpoint, ns=(mtime, mtime))  # each save a time of its own, however fast the filesystem's clock
        run.keep_checkpoints(job, seen)
        assert not kept.exists() if step < 4096 else torch.load(kept, weights_only=True)["global_step"] == 4096
    # Through the runner, with a real run that saves after each of its 4 iterations.
    job.run_dir.joinpath("checkpoint.pt").unlink()
    kept.unlink()
    assert run.run_grid([job], 1, save_every=1, status_every=1, results_root=tmp_path) == 0
    assert 4096 <= torch.load(kept, weights_only=True)["global_step"] <= 4 * 2048
    assert list(job.run_dir.glob("*.tmp")) == []


def test_a_variant_with_a_budget_of_its_own_runs_to_it_in_the_suites_folder(tmp_path):
    """roboschool-bullet runs the flagrun tasks to 100M and the forward walk to 50M: each variant's jobs take its own
    budget into the suite's one folder (its report and README line), and the forward walk keeps no checkpoint at its
    last step as a midway one; --total-timesteps puts every run at that budget in a folder of its own."""
    jobs = run.make_grid("roboschool-bullet", seeds=[1], results_root=tmp_path / "results", runs_root=tmp_path / "runs")
    budgets = {job.env_id.split(":")[-1]: job.total_timesteps for job in jobs}
    assert budgets == {
        "HumanoidForward-v0": 50_003_968,
        "HumanoidFlagrun-v0": 100_007_936,
        "HumanoidFlagrunHarder-v0": 100_007_936,
    }
    assert {job.results_dir for job in jobs} == {tmp_path / "results" / "roboschool-bullet"}
    assert {job.run_dir.parent for job in jobs} == {tmp_path / "runs" / "roboschool-bullet"}
    assert all(f"--total-timesteps {job.total_timesteps}" in " ".join(job.command()) for job in jobs)
    for job in jobs:  # a save at 50,003,968: kept midway for the 100M runs, not for the 50M walk that ends there
        job.run_dir.mkdir(parents=True)
        torch.save({"global_step": 50_003_968}, job.checkpoint)
        run.keep_checkpoints(job, {})
        assert (job.run_dir / "checkpoint_50M.pt").exists() == (job.total_timesteps > 50_003_968), job.name
    other = run.make_grid("roboschool-bullet", seeds=[1], total_timesteps=10_027_008, results_root=tmp_path)
    assert {(job.total_timesteps, job.results_dir.name) for job in other} == {
        (10_027_008, "roboschool-bullet_10027008")
    }


def test_the_rlhf_suite_keeps_its_series_and_samples_and_reports_them(tmp_path):
    rlhf = load_script("ppo_rlhf.py")
    job = run.make_grid("rlhf", ["beta0.05"], seeds=[1], results_root=tmp_path / "results", runs_root=tmp_path)[0]
    assert "--total-episodes 12800" in " ".join(job.command()) and "--env-id" not in job.command()
    # A tiny run in the job's folder, as if the runner had made it, with the log the runner keeps.
    tiny = dict(d_model=16, n_layer=1, n_head=2, response_length=16, sft_steps=60, sft_learning_rate=0.01, rm_pairs=128)
    tiny |= dict(rm_epochs=1, rm_batch_size=32, total_episodes=64, batch_size=16, minibatch_size=8, torch_threads=1)
    rlhf.train(rlhf.Args(**tiny, run_dir=str(job.run_dir)))
    (job.run_dir / "log.txt").write_text(
        "stage 3, PPO: iteration 4/4\n  score +1.00 | gold  +2 | the film was good <eos>\n"
    )
    run.finish(job)
    series = (job.results_dir / "rlhf" / f"{job.name}.csv").read_text().splitlines()
    assert series[0] == "global_step," + ",".join(RLHF_STATS) and len(series) == 1 + 4
    best = ["# wall_time_s: 60", ",".join(BEST_OF_N), "1,0,0.1,1.5,1,0,0,0.9", "4,0.636,0.9,3.25,0.5,0.5,0,nan"]
    (job.results_dir / "best_of_n").mkdir()
    (job.results_dir / "best_of_n" / "seed1.csv").write_text("\n".join(best) + "\n")
    text = report.report(job.results_dir)
    assert "| beta0.05 | " in text and "the film was good" in text and "| beta0.05 | 1 | " in text
    assert "## Best-of-N from pi_SFT (seeds 1)" in text and "1.0 min in all" in text
    assert "| 4 | 0.64 (1) | 0.90 (1) | 3.25 (1) | 0.50 (1) | 0.50 (1) | 0.00 (1) | – |" in text
    assert (job.results_dir / "curves" / "seeds.png").exists()
