"""The GPU path: each script trains on --device cuda, a CUDA checkpoint evaluates and resumes on the CPU, and
one update on CUDA is the CPU's, to float tolerance. Skipped where there is no CUDA, as in CI; run it where there is:

    python -m pytest tests/test_cuda.py
"""

import subprocess
import sys

import pytest
import ranks_worker
import torch
from conftest import ONE_THREAD, ROOT, TINY, load_script, run_cli, train_tiny

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA on this machine")

GYM = [
    ("ppo_continuous.py", []),
    ("ppo_kl_penalty.py", []),
    ("ppo_atari.py", []),
    ("ppo_atari.py", ["--compile"]),
]


@pytest.mark.parametrize("script,extra", GYM, ids=["continuous", "kl_penalty", "atari", "atari-compile"])
def test_each_script_trains_on_cuda(script, extra, tmp_path):
    run_dir, proc = train_tiny(script, tmp_path, "run", "--device", "cuda", *extra)
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True, map_location="cpu")
    assert checkpoint["global_step"] > 0 and checkpoint["args"]["device"] == "cuda"
    assert all(torch.isfinite(v).all() for v in checkpoint["agent"].values() if isinstance(v, torch.Tensor))


def test_the_rlhf_stages_run_on_cuda_which_auto_picks(tmp_path):
    run_cli("ppo_rlhf.py", *TINY["ppo_rlhf.py"]["tiny"], "--run-dir", tmp_path / "run", cwd=tmp_path)  # --device auto
    for stage in ("sft.pt", "reward_model.pt", "checkpoint.pt"):
        saved = torch.load(tmp_path / "run" / stage, weights_only=True)  # tensors come back on the device they had
        weights = saved["agent" if stage == "checkpoint.pt" else "model"]
        assert all(t.is_cuda for t in weights.values() if isinstance(t, torch.Tensor)), stage


@pytest.mark.parametrize("script", ["ppo_continuous.py", "ppo_atari.py"])
def test_a_cuda_checkpoint_evaluates_and_resumes_on_the_cpu(script, tmp_path):
    run_dir, _ = train_tiny(script, tmp_path, "run", "--device", "cuda")
    checkpoint = run_dir / "checkpoint.pt"
    proc = run_cli(script, "--eval-checkpoint", checkpoint, "--eval-episodes", "1", "--device", "cpu", cwd=tmp_path)
    assert "over 1 episodes" in proc.stdout
    saved = torch.load(checkpoint, weights_only=True, map_location="cpu")
    longer = {**saved, "args": {**saved["args"], "total_timesteps": saved["global_step"] * 2}}
    torch.save(longer, checkpoint)
    run_cli(script, "--resume", checkpoint, "--device", "cpu", cwd=tmp_path)
    assert torch.load(checkpoint, weights_only=True)["global_step"] == saved["global_step"] * 2


@pytest.mark.parametrize("script", ["ppo_continuous.py", "ppo_kl_penalty.py", "ppo_atari.py"])
def test_one_rollout_step_and_update_on_cuda_is_the_cpus(script):
    module = load_script(script)
    results = {}
    for device in ("cpu", "cuda"):
        agent, batch = ranks_worker.fixed_batch(module, script)  # the same weights and batch, made on the CPU
        agent = agent.to(device)
        batch = {key: value.to(device) for key, value in batch.items()}
        with torch.no_grad():  # the rollout's step: log-probs and values of the taken actions
            _, logprobs, _, values = agent.get_action_and_value(batch["obs"], batch["actions"])
        shuffles = {epoch: [i.to(device) for i in ranks_worker.minibatches(0, 1, epoch)[0]] for epoch in range(2)}
        ranks_worker.update(module, script, agent, batch, 0, 1, shuffles.get)
        results[device] = (
            logprobs.cpu(),
            values.cpu(),
            {k: v.cpu() for k, v in agent.state_dict().items() if isinstance(v, torch.Tensor)},
        )
    (lp_cpu, v_cpu, w_cpu), (lp_gpu, v_gpu, w_gpu) = results["cpu"], results["cuda"]
    torch.testing.assert_close(lp_gpu, lp_cpu, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(v_gpu, v_cpu, rtol=1e-4, atol=1e-5)
    for key in w_cpu:
        torch.testing.assert_close(w_gpu[key], w_cpu[key], rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="nccl between ranks needs a GPU for each of 2 ranks")
def test_two_ranks_on_two_gpus_end_with_the_same_weights(tmp_path):
    out = tmp_path / "result"
    flags = ["--env-id", "Hopper-v5", *TINY["ppo_continuous.py"]["tiny"], "--num-envs", "2", "--device", "cuda"]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]
    cmd += [str(ROOT / "tests" / "ranks_worker.py"), "main", "ppo_continuous.py", str(out), "--", *flags, *ONE_THREAD]
    cmd += ["--run-dir", str(tmp_path / "run")]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ranks = [torch.load(f"{out}.rank{r}.pt", weights_only=False, map_location="cpu") for r in range(2)]
    for key, value in ranks[0]["agent"].items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, ranks[1]["agent"][key]), key
