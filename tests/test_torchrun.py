"""One run in many processes: `torchrun --nproc-per-node P <script>` runs one Algorithm 1 in P ranks
over gloo, on this machine's CPUs. The update is the same math as one process's on the whole batch, the ranks end
with the same weights, the run keeps one record, and stops, dead ranks, bad input, resumes and two nodes behave.
Every test starts real processes: tests/ranks_worker.py under torchrun, or the scripts' own command line."""

import os
import signal
import socket
import subprocess
import sys
import time

import pytest
import ranks_worker
import torch
from conftest import ONE_THREAD, ROOT, TINY, load_script, signal_at_checkpoint, tb_scalars

GYM_SCRIPTS = ["ppo_continuous.py", "ppo_kl_penalty.py", "ppo_atari.py"]
# Each script's tiny run, with its envs split over 2 ranks (the MuJoCo scripts' tiny run has one env).
TWO_RANKS = {
    "ppo_continuous.py": ["--num-envs", "2"],
    "ppo_kl_penalty.py": ["--num-envs", "2"],
    "ppo_atari.py": [],
}
# The rules that read the batch's KL after each update, on: Table 4's step size (ppo_kl_penalty.py's beta is on by
# default; ppo_atari.py has none).
KL_RULES = {
    "ppo_continuous.py": ["--lr-target-kl", "0.01", "--no-anneal-lr"],
    "ppo_kl_penalty.py": [],
    "ppo_atari.py": [],
}


def torchrun(*args, nproc=2, standalone=True):
    """The command line of torchrun with `nproc` ranks on this machine (a free port of its own: --standalone)."""
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        *(["--standalone"] * standalone),
        f"--nproc-per-node={nproc}",
    ]


ENV = {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}


def run(cmd, cwd, timeout=240):
    return subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True, timeout=timeout)


def start(cmd, cwd):
    """A command left running, for a test to signal or kill."""
    return subprocess.Popen(cmd, cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(path, seconds=120):
    deadline = time.time() + seconds
    while not path.exists() and time.time() < deadline:
        time.sleep(0.02)


def tiny_flags(script, tmp_path, *extra, budget="tiny"):
    two_ranks = ["--num-envs", "2"] if budget == "interruptible" else TWO_RANKS[script]  # its interruptible run: 1 env
    return ["--env-id", TINY[script]["env_id"], *TINY[script][budget], *two_ranks, *ONE_THREAD, *extra]


def worker_main(script, tmp_path, flags, nproc=2, timeout=240):
    """The script's main() in `nproc` ranks (ranks_worker.py): (CompletedProcess, each rank's saved result)."""
    out = tmp_path / "result"
    cmd = [*torchrun(nproc=nproc), str(ROOT / "tests" / "ranks_worker.py"), "main", script, str(out), "--", *flags]
    proc = run(cmd, tmp_path, timeout)
    results = [
        torch.load(f"{out}.rank{r}.pt", weights_only=False) for r in range(nproc) if os.path.exists(f"{out}.rank{r}.pt")
    ]
    return proc, results


def assert_same_state(a, b):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], torch.Tensor):
            assert torch.equal(a[key], b[key]), key
        else:  # the normalizers' statistics
            for name in a[key]:
                assert torch.equal(torch.as_tensor(a[key][name]), torch.as_tensor(b[key][name])), (key, name)


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_one_update_on_two_ranks_is_one_process_update_on_the_whole_batch(script, tmp_path):
    out = tmp_path / "update"
    proc = run([*torchrun(), str(ROOT / "tests" / "ranks_worker.py"), "update", script, str(out)], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ranks = [torch.load(f"{out}.rank{r}.pt", weights_only=False) for r in range(2)]
    assert_same_state(ranks[0]["agent"], ranks[1]["agent"])  # every rank holds the same weights after every step

    module = load_script(script)
    start, batch = ranks_worker.fixed_batch(module, script)
    before = {k: v.clone() for k, v in start.state_dict().items() if isinstance(v, torch.Tensor)}
    # One process on the whole batch, each minibatch the union of the ranks' shares of it.
    whole = ranks_worker.update(module, script, start, batch, 0, 1, lambda e: ranks_worker.minibatches(0, 2, e)[1])
    for key, value in whole.state_dict().items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            assert not torch.equal(value, before[key]) or key.endswith("logstd"), f"{key} did not move"
            torch.testing.assert_close(ranks[0]["agent"][key], value, rtol=1e-5, atol=1e-6)
    # The comparison can fail: one rank's half alone, without the other's gradients, is another update.
    alone, _ = ranks_worker.fixed_batch(module, script)
    half = {key: value[: ranks_worker.B // 2] for key, value in batch.items()}
    ranks_worker.update(module, script, alone, half, 0, 1, lambda e: ranks_worker.minibatches(0, 2, e)[0])
    differs = [
        not torch.allclose(alone.state_dict()[k], v, atol=1e-6) for k, v in whole.state_dict().items() if "weight" in k
    ]
    assert any(differs)

    if "rms" in ranks[0]:  # the normalizer: the merged statistics of the ranks' halves are those of all the data
        rms = module.RunningMeanStd((7,))
        for step in range(12):
            rms.update(ranks_worker.observations(step, 1, 0))
        for rank in ranks:
            for merged, single in zip(rank["rms"], (rms.mean, rms.var, rms.count), strict=True):
                torch.testing.assert_close(torch.as_tensor(merged), torch.as_tensor(single), rtol=1e-10, atol=1e-10)
        assert rms.count == pytest.approx(48 + 1e-4)  # 12 steps of 4 envs, and the prior's epsilon


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_two_rank_run_ends_with_the_same_weights_on_both_ranks_and_one_record(script, tmp_path):
    flags = tiny_flags(script, tmp_path, "--run-dir", str(tmp_path / "run"), *KL_RULES[script])
    proc, ranks = worker_main(script, tmp_path, flags)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [r["exit"] for r in ranks] == [0, 0]
    assert_same_state(ranks[0]["agent"], ranks[1]["agent"])
    # The KL that the step size's or beta's rule reads is the mean over all ranks, the same on each: a rank's
    # own KL would give each rank its own step size or beta, and their weights would drift apart over the run.
    if script != "ppo_atari.py":
        assert len(ranks[0]["kls"]) >= 1 and ranks[0]["kls"] == ranks[1]["kls"], [r["kls"] for r in ranks]
    # Env i of the run is seeded as env i of one process, (seed + step) N + i, whichever rank steps it: ranks
    # that seeded their envs as rank 0 does would start half of each batch from the same states.
    n_envs = int(flags[flags.index("--num-envs") + 1]) if "--num-envs" in flags else 1
    assert ranks[0]["seeds"][0] + ranks[1]["seeds"][0] == [1 * n_envs + i for i in range(n_envs)]
    # One record: rank 0's TensorBoard file and checkpoint, one set of progress lines, and every rank's episodes.
    run_dir = tmp_path / "run"
    assert len(list(run_dir.glob("events.out.tfevents.*"))) == 1
    assert_same_state(torch.load(run_dir / "checkpoint.pt", weights_only=True)["agent"], ranks[0]["agent"])
    assert proc.stdout.count("saved ") == 1, proc.stdout
    episodes = [r["episodes"] for r in ranks]
    assert min(episodes) > 0, episodes
    assert len(tb_scalars(run_dir)["charts/episodic_return"]) == sum(episodes)
    # main() leaves the process group, and nothing holds it after: gloo's threads, still running as the interpreter
    # exits, can abort a rank that has finished (the reason torch._dynamo is imported before the group).
    for rank in ranks:
        assert rank["threads"] is None or not [t for t in rank["threads"] if "gloo" in t], rank["threads"]


def test_ctrl_c_stops_every_rank_at_one_iteration_with_one_checkpoint(tmp_path):
    script = "ppo_continuous.py"
    run_dir = tmp_path / "run"
    flags = tiny_flags(script, tmp_path, "--run-dir", str(run_dir), "--save-every", "2", budget="interruptible")
    out = tmp_path / "result"
    cmd = [*torchrun(), str(ROOT / "tests" / "ranks_worker.py"), "main", script, str(out), "--", *flags]
    proc = start(cmd, tmp_path)
    try:
        wait_for(run_dir / "checkpoint.pt")
        # Ctrl-C in a terminal signals the whole foreground group: torchrun and each of its ranks.
        for pid in [
            proc.pid,
            *subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split(),
        ]:
            os.kill(int(pid), signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    ranks = [torch.load(f"{out}.rank{r}.pt", weights_only=False) for r in range(2)]
    assert [r["exit"] for r in ranks] == [130, 130], stderr[-3000:]
    assert_same_state(ranks[0]["agent"], ranks[1]["agent"])  # the same iteration: no rank updated once more
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert_same_state(checkpoint["agent"], ranks[0]["agent"])
    assert checkpoint["global_step"] < 2048
    assert stdout.count("continue with --resume") == 1, stdout


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_a_sigterm_to_one_rank_alone_stops_every_rank_at_one_iteration_with_one_checkpoint(script, tmp_path):
    """A scheduler that preempts one machine signals its ranks only. The others stop with it, at the same
    iteration, and rank 0 saves: a rank that stopped on its own flag would leave the others to fail (rank 0 saving
    nothing since its last checkpoint)."""
    run_dir = tmp_path / "run"
    flags = tiny_flags(script, tmp_path, "--run-dir", str(run_dir), "--save-every", "2", budget="interruptible")
    out = tmp_path / "result"
    proc = start(
        [*torchrun(), str(ROOT / "tests" / "ranks_worker.py"), "main", script, str(out), "--", *flags], tmp_path
    )
    try:
        wait_for(run_dir / "checkpoint.pt")
        saved = (run_dir / "checkpoint.pt").stat().st_mtime_ns
        children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        rank1 = [pid for pid in children if "RANK=1" in open(f"/proc/{pid}/environ", "rb").read().decode().split("\0")]
        assert len(rank1) == 1, children
        os.kill(int(rank1[0]), signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    ranks = [
        torch.load(f"{out}.rank{r}.pt", weights_only=False) for r in range(2) if os.path.exists(f"{out}.rank{r}.pt")
    ]
    assert [r["exit"] for r in ranks] == [130, 130], stderr[-3000:]
    assert_same_state(ranks[0]["agent"], ranks[1]["agent"])
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert_same_state(checkpoint["agent"], ranks[0]["agent"])  # saved at the stop
    assert (run_dir / "checkpoint.pt").stat().st_mtime_ns > saved and checkpoint["global_step"] < 2048
    assert stdout.count("continue with --resume") == 1, stdout


def test_sigterm_to_torchrun_stops_the_run_with_one_checkpoint(tmp_path):
    script = "ppo_kl_penalty.py"
    run_dir = tmp_path / "run"
    cmd = [
        *torchrun(),
        str(ROOT / script),
        *tiny_flags(script, tmp_path, "--run-dir", str(run_dir), budget="interruptible"),
    ]
    proc = start(cmd, tmp_path)
    stdout, stderr = signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGTERM, wait=120)
    # torchrun forwards the signal to its ranks; they stop together and rank 0 saves. torchrun itself then reports the
    # signal it got (its own exit status, not the ranks').
    assert stdout.count("continue with --resume") == 1, stdout + stderr[-3000:]
    assert 'ppo_kl_penalty.py", line' not in stderr  # no traceback of the script's
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert 0 < checkpoint["global_step"] < 2048


def test_a_rank_that_dies_ends_the_others_with_one_line(tmp_path):
    script = "ppo_continuous.py"
    run_dir = tmp_path / "run"
    cmd = [
        *torchrun(),
        str(ROOT / script),
        *tiny_flags(script, tmp_path, "--run-dir", str(run_dir), budget="interruptible"),
    ]
    proc = start(cmd, tmp_path)
    try:
        wait_for(run_dir / "checkpoint.pt")
        children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        ranks = [pid for pid in children if "--env-id" in open(f"/proc/{pid}/cmdline").read().replace("\0", " ")]
        assert len(ranks) == 2, children
        os.kill(int(max(ranks, key=int)), signal.SIGKILL)  # the rank started last
        killed_at = time.time()
        _, stderr = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert time.time() - killed_at < 60  # ended, not hung
    assert proc.returncode != 0
    ours = [line for line in stderr.splitlines() if "ppo_continuous.py: error" in line]
    assert len(ours) == 1 and "lost another rank" in ours[0], stderr[-3000:]
    assert 'ppo_continuous.py", line' not in stderr  # no traceback of the script's


@pytest.mark.parametrize(
    "flags,message",
    [
        (["--num-envs", "3"], "torchrun's 2 processes must divide --num-envs 3"),
        (
            ["--num-envs", "2", "--minibatch-size", "33", "--num-steps", "66"],
            "must divide --num-envs 2 and --minibatch-size 33",
        ),
        (["--num-envs", "2", "--device", "cuda"], "--device cuda is not available here"),
    ],
)
def test_bad_input_is_refused_by_every_rank_before_any_env_starts(flags, message, tmp_path):
    if "cuda" in flags and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    proc = run([*torchrun(), str(ROOT / "ppo_continuous.py"), *flags, "--total-timesteps", "10000"], tmp_path)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if "ppo_continuous.py: error" in line]
    # Each rank checks its input; torchrun ends the others as soon as one has refused, so one line or two.
    assert 1 <= len(lines) <= 2 and all(message in line for line in lines), proc.stderr[-3000:]
    assert not (tmp_path / "runs").exists()


def test_a_checkpoint_of_two_ranks_resumes_with_two_ranks_or_one_and_evaluates_in_one_process(tmp_path):
    script = "ppo_continuous.py"
    run_dir = tmp_path / "run"
    flags = tiny_flags(script, tmp_path, "--run-dir", str(run_dir), "--total-timesteps", "384")
    proc = run([*torchrun(), str(ROOT / script), *flags], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert checkpoint["global_step"] == 384
    # The run's own budget comes back from the checkpoint; a longer one needs a new run, so resume a copy whose saved
    # budget is raised by hand, with 2 ranks and with 1.
    for name, launcher in (("two", torchrun()), ("one", [sys.executable])):
        folder = tmp_path / name
        folder.mkdir()
        longer = {**checkpoint, "args": {**checkpoint["args"], "total_timesteps": 640}}
        torch.save(longer, folder / "checkpoint.pt")
        proc = run([*launcher, str(ROOT / script), "--resume", str(folder / "checkpoint.pt"), *ONE_THREAD], tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert f"resuming {folder}" in proc.stdout and proc.stdout.count("resuming") == 1
        resumed = torch.load(folder / "checkpoint.pt", weights_only=True)
        assert resumed["global_step"] == 640 and resumed["iteration"] == 5
        assert not torch.equal(resumed["agent"]["actor_mean.0.weight"], checkpoint["agent"]["actor_mean.0.weight"])
    proc = run(
        [
            sys.executable,
            str(ROOT / script),
            "--eval-checkpoint",
            str(run_dir / "checkpoint.pt"),
            "--eval-episodes",
            "2",
        ],
        tmp_path,
    )
    assert proc.returncode == 0 and "over 2 episodes" in proc.stdout, proc.stderr[-3000:]


def test_a_one_process_checkpoint_resumes_with_two_ranks(tmp_path):
    script = "ppo_atari.py"
    run_dir = tmp_path / "run"
    proc = run([sys.executable, str(ROOT / script), *tiny_flags(script, tmp_path, "--run-dir", str(run_dir))], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    longer = {**checkpoint, "args": {**checkpoint["args"], "total_timesteps": checkpoint["global_step"] + 384}}
    torch.save(longer, run_dir / "checkpoint.pt")
    proc = run([*torchrun(), str(ROOT / script), "--resume", str(run_dir / "checkpoint.pt"), *ONE_THREAD], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["global_step"] == longer["args"]["total_timesteps"]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_nodes_on_this_machine_run_one_run(tmp_path):
    """Two torchrun processes, one a node, meeting at a c10d rendezvous on 127.0.0.1, as on two machines."""
    script = "ppo_continuous.py"
    port = free_port()
    out = tmp_path / "result"
    flags = tiny_flags(script, tmp_path, "--run-dir", str(tmp_path / "run"))
    node = [sys.executable, "-m", "torch.distributed.run", "--nnodes=2", "--nproc-per-node=1", "--rdzv-backend=c10d"]
    node += [f"--rdzv-endpoint=127.0.0.1:{port}", "--rdzv-id=two-nodes"]
    cmd = [*node, str(ROOT / "tests" / "ranks_worker.py"), "main", script, str(out), "--", *flags]
    nodes = [start(cmd, tmp_path) for _ in range(2)]
    try:
        outputs = [p.communicate(timeout=240) for p in nodes]
    finally:
        for p in nodes:
            if p.poll() is None:
                p.kill()
    assert [p.returncode for p in nodes] == [0, 0], [o[1][-2000:] for o in outputs]
    ranks = [torch.load(f"{out}.rank{r}.pt", weights_only=False) for r in range(2)]
    assert_same_state(ranks[0]["agent"], ranks[1]["agent"])
    assert (tmp_path / "run" / "checkpoint.pt").exists()


@pytest.mark.parametrize("script", GYM_SCRIPTS)
def test_compile_under_torchrun_is_refused_in_one_line_before_the_run(script, tmp_path):
    """--compile is for one process. Under torchrun the compiled update's graph holds the process group that
    its all-gather of the advantages uses, past destroy_process_group to the interpreter's exit, and gloo's threads with
    it: the state in which a finished rank can abort (the test of a two-rank run above checks that none is left)."""
    flags = tiny_flags(script, tmp_path, "--run-dir", str(tmp_path / "run"), "--compile")
    proc = run([*torchrun(), str(ROOT / script), *flags], tmp_path)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if f"{script}: error" in line]
    assert 1 <= len(lines) <= 2, proc.stderr[-3000:]  # each rank refuses; torchrun may end the other first
    assert all("--compile is for one process; run torchrun without it" in line for line in lines), lines
    assert not (tmp_path / "run").exists()
    assert f'{script}", line' not in proc.stderr  # no traceback of the script's (torchrun prints its own)
