"""The benchmarks' tools beside the runner: throughput.py, film.py, best_of_n.py and sb3_mujoco.py's hyperparameters."""

import json
import math
import subprocess
import sys

import pytest
import torch
from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
from common import load_script  # noqa: E402
from run import make_grid  # noqa: E402


def test_throughput_replaces_only_its_own_section(tmp_path):
    import throughput

    path = tmp_path / "throughput.md"
    throughput.write_section(path, "mujoco", "## mujoco\n\n| a | 1 |\n")
    throughput.write_section(path, "atari", "## atari\n\n| b | 2 |\n")
    throughput.write_section(path, "mujoco", "## mujoco\n\n| a | 3 |\n")
    text = path.read_text()
    assert text.startswith("# Throughput") and "| a | 3 |" in text and "| a | 1 |" not in text
    assert "| b | 2 |" in text and text.index("## mujoco") < text.index("## atari")
    assert text.count("<!-- suite: mujoco -->") == 1


def test_sb3_mujoco_reads_the_rl_zoos_entry_for_the_task():
    pytest.importorskip("rl_zoo3")
    sb3 = load_script("benchmarks/sb3_mujoco.py")
    params, source = sb3.hyperparameters("trpo", "HalfCheetah-v5")
    assert source == "rl_zoo3 hyperparams/trpo.yml, entry HalfCheetah-v4" and params["normalize"] is True
    assert params["target_kl"] == 0.04 and params["n_envs"] == 2  # the task's own entry, over the shared defaults
    params, source = sb3.hyperparameters("a2c", "Reacher-v5")
    assert source.endswith("entry default (the Zoo has no entry for this task: SB3's defaults)")
    assert "normalize" not in params and params["policy"] == "MlpPolicy"


def test_film_records_the_runs_policy_and_a_frame_of_it(tmp_path, tiny_run):
    import film
    import imageio.v3 as iio

    (job,) = make_grid("mujoco", envs=["Hopper"], seeds=[1], runs_root=tmp_path / "runs")
    job.run_dir.mkdir(parents=True)
    with pytest.raises(ValueError, match="has no checkpoint"):
        film.film(job, tmp_path / "video")
    torch.save(torch.load(tiny_run("ppo_continuous.py")[0] / "checkpoint.pt", weights_only=True), job.checkpoint)
    video, line = film.film(job, tmp_path / "video")
    assert video == tmp_path / "video" / "Hopper-v5__clip0.2__seed1.mp4" and line.startswith("eval Hopper-v5 step ")
    frame = iio.imread(video.with_suffix(".png"))
    assert frame.ndim == 3 and frame.std() > 0, "a frame of the film, not a blank"
    assert not list(job.run_dir.glob("videos-eval")), "the run's own folder is left as it was"


def test_throughput_humanoid_case_measures_ours_sb3_and_the_envs_with_table4(capsys):
    import throughput

    flags = throughput.SUITES["humanoid"]["flags"]
    assert "--num-envs 32 --num-steps 512 --update-epochs 15 --minibatch-size 4096" in flags
    # Table 4 on a tiny rollout (the case's flags come after the suite's): 3 iterations of 32 x 8 steps
    sps, first = throughput.measure_ours(
        "ppo_continuous.py --num-steps 8 --minibatch-size 128", "Humanoid-v5", 768, flags
    )
    assert sps > 0 and first > 0
    throughput.run_worker("env", "Humanoid-v5", 64, "humanoid")  # the 32 envs of ppo_continuous.py, alone
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["sps"] > 0
    # The 2-rank case: the same train() in two processes under torchrun, timed by rank 0.
    sps, first = throughput.measure(
        "torchrun --nproc-per-node 2 ppo_continuous.py --num-steps 8 --minibatch-size 128",
        "Humanoid-v5",
        768,
        "humanoid",
    )
    assert sps > 0 and first > 0
    pytest.importorskip("stable_baselines3")  # benchmarks/requirements.txt; .ci/run installs it
    tiny = dict(n_envs=32, n_steps=8, batch_size=128, n_epochs=1)
    sps, first = throughput.measure_sb3_ppo_mujoco("Humanoid-v5", 768, threads=1, **tiny)
    assert sps > 0 and first > 0


def test_throughput_reads_the_workers_result_when_another_rank_prints_after_it(monkeypatch):
    import throughput

    # Under torchrun every rank's stdout is one pipe: rank 1's own last line may come after rank 0's result.
    stdout = '{"sps": 5.0, "first_iteration_s": 1.0}\nsaved /tmp/rank1/checkpoint.pt\n'
    done = subprocess.CompletedProcess([], 0, stdout=stdout, stderr="")
    monkeypatch.setattr(throughput.subprocess, "run", lambda *args, **kwargs: done)
    case = "torchrun --nproc-per-node 2 ppo_continuous.py"
    assert throughput.measure(case, "Humanoid-v5", 768, "humanoid") == (5.0, 1.0)


def test_best_of_n_keeps_the_rm_favourite_of_n_with_its_analytic_kl(tmp_path):
    import best_of_n

    assert best_of_n.analytic_kl(1) == 0 and best_of_n.analytic_kl(4) == pytest.approx(math.log(4) - 0.75)
    rlhf_tiny = (
        "--d-model 16 --n-layer 1 --n-head 2 --response-length 16 --sft-steps 60 --sft-learning-rate 0.01"
        " --rm-pairs 128 --rm-epochs 1 --rm-batch-size 32 --total-episodes 16 --batch-size 16 --minibatch-size 8"
    ).split()
    cmd = [sys.executable, str(ROOT / "ppo_rlhf.py"), *rlhf_tiny, "--torch-threads", "1", "--run-dir", "run"]
    subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True, timeout=300)
    rows = best_of_n.best_of_n(tmp_path / "run", prompts=16, ns=[1, 2, 8])
    assert [row[0] for row in rows] == [1, 2, 8] and [row[1] for row in rows] == [
        best_of_n.analytic_kl(n) for n in (1, 2, 8)
    ]
    scores = [row[2] for row in rows]
    assert scores[0] <= scores[1] <= scores[2], "the best of more responses (nested: the first N) scores no lower"
    assert all(row[4] + row[5] + row[6] == pytest.approx(1.0) for row in rows), "each kept response has one form"
    assert all(math.isnan(row[7]) or 0 <= row[7] <= 1 for row in rows), "the RM's accuracy on the kept responses"


def test_best_of_ns_closed_form_kl_is_an_upper_bound_measured_by_enumeration():
    """On a small discrete distribution, the KL of best-of-n counted over every n-tuple of draws is
    exact_kl's, at most log n - (n - 1) / n, and near it when no response has much mass."""
    import itertools

    import best_of_n

    probs = [0.4, 0.3, 0.2, 0.1]
    scores = [0.5, -1.0, 2.0, 0.1]
    for n in (1, 2, 3, 4):
        kept = [0.0] * len(probs)
        for draw in itertools.product(range(len(probs)), repeat=n):
            weight = math.prod(probs[i] for i in draw)
            kept[max(draw, key=lambda i: scores[i])] += weight
        by_enumeration = sum(q * math.log(q / p) for q, p in zip(kept, probs, strict=True) if q > 0)
        assert best_of_n.exact_kl(probs, scores, n) == pytest.approx(by_enumeration, abs=1e-12)
        assert by_enumeration <= best_of_n.analytic_kl(n) + 1e-12
    assert best_of_n.exact_kl(probs, scores, 4) < best_of_n.analytic_kl(4) - 0.05  # heavy atoms: far below the bound
    fine = [1 / 10_000] * 10_000  # no response with much mass: the bound is nearly reached
    assert best_of_n.exact_kl(fine, list(range(10_000)), 64) == pytest.approx(best_of_n.analytic_kl(64), abs=2e-3)


def test_best_of_n_scores_an_ensemble_arm_with_its_aggregate(tmp_path):
    """An ensemble arm's reward_model.pt holds its K members and the aggregate its run scored with: best_of_n.py loads
    them as the run did and keeps the response their aggregate scores highest. Members: one network s, and the same
    with its score 4 higher. Per response, min is s, mean s + 2 and uwo s + 2 - 0.1 var = s + 1.2 (var of {s, s + 4} is
    8, with ddof 1): each ensemble's rows are those of the one network with its score shifted so (a response without
    EOS scores the run's fixed --no-eos-score under both); and its CSV goes to a folder of its own, not over the single
    reward model's."""
    import best_of_n

    rlhf = load_script("ppo_rlhf.py")
    args = rlhf.Args(d_model=16, n_layer=1, n_head=2, response_length=16, seed=1)
    torch.manual_seed(0)
    sft, single = rlhf.new_model(args, "cpu"), rlhf.new_model(args, "cpu")
    torch.nn.init.normal_(single.score_head.weight)  # a zero head scores every response 0: no favourite

    def rows_of(name, rm_args, state):
        (tmp_path / name).mkdir()
        rlhf.save_checkpoint(str(tmp_path / name / "sft.pt"), "sft", args, model=sft.state_dict())
        rlhf.save_checkpoint(str(tmp_path / name / "reward_model.pt"), "reward_model", rm_args, model=state)
        return best_of_n.best_of_n(tmp_path / name, prompts=16, ns=[1, 4, 16])

    plain = rows_of("single", args, single.state_dict())
    assert plain[0][2] < plain[-1][2], "the single RM must have a favourite for the check to mean anything"
    for agg, shift in (("min", 0.0), ("mean", 2.0), ("uwo", 1.2)):
        ensemble_args = rlhf.Args(**{**vars(args), "rm_ensemble": 2, "rm_ensemble_agg": agg})
        ensemble = rlhf.new_model(ensemble_args, "cpu", members=2)
        for member in ensemble:
            member.load_state_dict(single.state_dict())
        shifted = rlhf.new_model(args, "cpu", single.state_dict())
        with torch.no_grad():
            ensemble[1].score_head.bias.add_(4.0)
            shifted.score_head.bias.add_(shift)
        mine = rows_of(agg, ensemble_args, ensemble.state_dict())
        theirs = rows_of(f"single+{shift}", args, shifted.state_dict())
        for row, expected in zip(mine, theirs, strict=True):
            assert row == pytest.approx(expected, abs=1e-4, nan_ok=True), agg
    results = tmp_path / "results"
    assert best_of_n.default_out(results, args) == results / "rlhf" / "best_of_n"
    min_args = rlhf.Args(**{**vars(args), "rm_ensemble": 2, "rm_ensemble_agg": "min"})
    assert best_of_n.default_out(results, min_args) == results / "rlhf-long" / "rm4096-ens2-min" / "best_of_n"


def test_best_of_n_scores_a_process_rm_by_the_sum_of_its_clauses(tmp_path):
    """A process RM's reward_model.pt: best_of_n.py reads it as its run did, each response's score the sum of the
    network's scalars at the response's "and" and EOS tokens (computed here by hand), not its scalar at the EOS alone;
    and its CSV goes to a folder of its own."""
    import best_of_n

    rlhf = load_script("ppo_rlhf.py")
    args = rlhf.Args(d_model=16, n_layer=1, n_head=2, response_length=16, seed=1, reward="process")
    torch.manual_seed(0)
    sft, prm = rlhf.new_model(args, "cpu"), rlhf.new_model(args, "cpu")
    torch.nn.init.normal_(prm.score_head.weight)
    rlhf.save_checkpoint(str(tmp_path / "sft.pt"), "sft", args, model=sft.state_dict())
    rlhf.save_checkpoint(str(tmp_path / "reward_model.pt"), "reward_model", args, model=prm.state_dict())
    rows = best_of_n.best_of_n(tmp_path, prompts=8, ns=[1, 4])
    torch.manual_seed(0)  # best_of_n's draw
    tokens, mask = rlhf.generate(sft, 8, args.response_length, args.temperature, 4)
    P = rlhf.PROMPT_LENGTH
    with torch.no_grad():
        scalars = prm(tokens)[1][:, P:]
    by_hand = []
    for i, row in enumerate(tokens[:, P:].tolist()):
        n = int(mask[i].sum())
        if rlhf.EOS not in row[:n]:
            by_hand.append(args.no_eos_score)
        else:
            by_hand.append(sum(scalars[i, j].item() for j in range(n) if row[j] in (rlhf.TOKEN["and"], rlhf.EOS)))
    by_hand = torch.tensor(by_hand).view(8, 4)
    assert rows[0][2] == pytest.approx(by_hand[:, 0].mean().item(), abs=1e-5)
    assert rows[1][2] == pytest.approx(by_hand.max(1).values.mean().item(), abs=1e-5)
    results = tmp_path / "results"
    assert best_of_n.default_out(results, args) == results / "rlhf-long" / "rm4096-process" / "best_of_n"
