"""ppo_rlhf.py: its math against plain loops and hand computations, its language, and its real command line on a tiny
budget (stop and resume, determinism, cached stages, bad input)."""

import copy
import math
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import ONE_THREAD, ROOT, TINY, load_script, rlhf_tiny_args, run_cli, signal_at_checkpoint, tb_scalars

SCRIPT = "ppo_rlhf.py"
rlhf = load_script(SCRIPT)
TINY_FLAGS = TINY[SCRIPT]["tiny"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One tiny run of all three stages in this process, shared by the tests that only read it."""
    path = tmp_path_factory.mktemp("rlhf")
    agent, run_dir = rlhf.train(rlhf_tiny_args(path))
    return agent, path / "run"


# THE MATH, against plain loops
def reference_rewards(scores, logprobs, ref_logprobs, mask, kl_coef):
    B, L = logprobs.shape
    rewards = np.zeros((B, L))
    for i in range(B):
        last = max(t for t in range(L) if mask[i, t])
        for t in range(last + 1):
            rewards[i, t] = -kl_coef * (logprobs[i, t] - ref_logprobs[i, t])
        rewards[i, last] += scores[i]
    return rewards


def reference_gae(rewards, values, mask, gamma, lam):
    """A forward double loop: A_t = sum_l (gamma lam)^l delta_{t+l} up to the end of the response, V = 0 after it."""
    B, L = rewards.shape
    adv = np.zeros((B, L))
    for i in range(B):
        end = max(t for t in range(L) if mask[i, t])
        for t in range(end + 1):
            for k in range(t, end + 1):
                next_value = values[i, k + 1] if k < end else 0.0
                adv[i, t] += (gamma * lam) ** (k - t) * (rewards[i, k] + gamma * next_value - values[i, k])
    return adv


def masks_with_a_row_without_eos(rng, B, L):
    lengths = rng.integers(1, L + 1, size=B)
    lengths[0] = L  # a response cut at the length limit, without an EOS: every position counts
    return (np.arange(L)[None] < lengths[:, None]).astype(np.float64)


def t64(*arrays):
    return [torch.tensor(a, dtype=torch.float64) for a in arrays]


@pytest.mark.parametrize("seed", range(5))
def test_rewards_match_a_plain_loop(seed):
    rng = np.random.default_rng(seed)
    B, L = 4, 7
    mask = masks_with_a_row_without_eos(rng, B, L)
    scores, logprobs, ref_logprobs = rng.normal(size=B), -rng.random((B, L)), -rng.random((B, L))
    expected = reference_rewards(scores, logprobs, ref_logprobs, mask, 0.3)
    rewards = rlhf.compute_rewards(*t64(scores, logprobs, ref_logprobs, mask), 0.3)
    np.testing.assert_allclose(rewards.numpy(), expected, atol=1e-12)


@pytest.mark.parametrize("gamma,lam", [(1.0, 0.95), (0.9, 0.5), (1.0, 1.0), (0.5, 0.0)])
def test_gae_matches_a_double_loop(gamma, lam):
    rng = np.random.default_rng(7)
    B, L = 5, 9
    mask = masks_with_a_row_without_eos(rng, B, L)
    rewards, values = rng.normal(size=(2, B, L)) * mask  # what the script passes: nothing after the end
    values_after_the_end = values + 100.0 * (1 - mask)  # must be ignored
    expected = reference_gae(rewards, values, mask, gamma, lam)
    adv, ret = rlhf.compute_gae(*t64(rewards, values_after_the_end, mask), gamma, lam)
    np.testing.assert_allclose(adv.numpy(), expected, atol=1e-9)
    np.testing.assert_allclose(ret.numpy(), (expected + values) * mask, atol=1e-9)


def test_gae_with_one_terminal_score_and_no_value_is_the_score_to_go():
    # gamma = lambda = 1, V = 0, and only the score at the EOS: every token's advantage is that score.
    mask = torch.tensor([[1.0, 1.0, 1.0, 0.0]])
    rewards = rlhf.compute_rewards(torch.tensor([2.5]), torch.zeros(1, 4), torch.zeros(1, 4), mask, 0.1)
    adv, _ = rlhf.compute_gae(rewards, torch.zeros(1, 4), mask, 1.0, 1.0)
    assert adv.tolist() == [[2.5, 2.5, 2.5, 0.0]]


def test_kl_controller_at_its_clip_bounds():
    # e = clip(KL / target - 1, -0.2, 0.2); beta <- beta (1 + e n / horizon).
    assert rlhf.adapt_kl_coef(0.1, 100.0, 6.0, 64, 1000) == pytest.approx(0.1 * (1 + 0.2 * 0.064))
    assert rlhf.adapt_kl_coef(0.1, 7.2, 6.0, 64, 1000) == pytest.approx(0.1 * (1 + 0.2 * 0.064))  # exactly at +0.2
    assert rlhf.adapt_kl_coef(0.1, 0.0, 6.0, 64, 1000) == pytest.approx(0.1 * (1 - 0.2 * 0.064))
    assert rlhf.adapt_kl_coef(0.1, 6.6, 6.0, 64, 1000) == pytest.approx(0.1 * (1 + 0.1 * 0.064))  # inside: e = 0.1
    assert rlhf.adapt_kl_coef(0.1, 6.0, 6.0, 64, 1000) == pytest.approx(0.1)
    assert rlhf.adapt_kl_coef(0.0, 100.0, 6.0, 64, 1000) == 0.0  # beta = 0 stays 0: the rule is multiplicative


def test_bradley_terry_loss_by_hand():
    # -log sigmoid(d) = log(1 + e^-d): for d = 1, 0 and -2, averaged.
    chosen, rejected = torch.tensor([2.0, 0.5, -1.0]), torch.tensor([1.0, 0.5, 1.0])
    by_hand = (math.log(1 + math.exp(-1)) + math.log(2) + math.log(1 + math.exp(2))) / 3
    assert rlhf.preference_loss(chosen, rejected).item() == pytest.approx(by_hand, rel=1e-6)


def group_advantages(rewards, mask, group_size, kind="grpo"):
    """The script's named group baseline (grpo_advantages, dr_grpo_advantages or rloo_advantages) of each response's
    summed reward, at each of its tokens, as group_baseline_update feeds the loss."""
    advantage = {"grpo": rlhf.grpo_advantages, "dr-grpo": rlhf.dr_grpo_advantages, "rloo": rlhf.rloo_advantages}[kind]
    return advantage(rewards.sum(1).view(-1, group_size)).view(-1, 1) * mask


def reference_group_advantages(rewards, mask, group_size):
    """GRPO's advantage, a response at a time: its summed reward against its group's mean and (n - 1) std."""
    out = np.zeros_like(rewards)
    returns = rewards.sum(1)
    for i in range(len(rewards)):
        group = returns[i // group_size * group_size : (i // group_size + 1) * group_size]
        out[i] = (returns[i] - group.mean()) / (group.std(ddof=1) + 1e-8) * mask[i]
    return out


@pytest.mark.parametrize("group_size", [2, 4])
def test_group_advantages_match_a_loop_over_responses(group_size):
    rng = np.random.default_rng(group_size)
    mask = masks_with_a_row_without_eos(rng, 8, 6)
    rewards = rng.normal(size=(8, 6)) * mask
    advantages = group_advantages(*t64(rewards, mask), group_size)
    np.testing.assert_allclose(advantages.numpy(), reference_group_advantages(rewards, mask, group_size), atol=1e-9)
    # A group whose responses all earn the same reward teaches nothing: its advantages are 0.
    same = group_advantages(torch.ones(4, 3), torch.ones(4, 3), 4)
    assert torch.equal(same, torch.zeros(4, 3))


def test_pairwise_accuracy_counts_only_pairs_to_one_prompt_as_a_loop_over_pairs_does():
    rng = np.random.default_rng(3)
    scores, gold, prompts = rng.normal(size=12), rng.integers(-2, 3, size=12).astype(float), rng.integers(0, 3, 12)
    pairs = [(i, j) for i in range(12) for j in range(12) if gold[i] > gold[j] and prompts[i] == prompts[j]]
    expected = sum(scores[i] > scores[j] for i, j in pairs) / len(pairs)
    accuracy, n_pairs = rlhf.pairwise_accuracy(*t64(scores, gold, prompts))
    assert accuracy.item() == pytest.approx(expected) and n_pairs == len(pairs) > 0
    assert rlhf.pairwise_accuracy(*t64(-scores, gold, prompts))[0].item() == pytest.approx(1 - expected)  # no ties
    # One prompt each: no pair counts, however the scores and gold differ
    assert torch.isnan(rlhf.pairwise_accuracy(*t64(scores, gold, np.arange(12)))[0]), "no pair to one prompt"
    assert torch.isnan(rlhf.pairwise_accuracy(torch.ones(3), torch.ones(3), torch.zeros(3))[0]), "no different gold"


def test_grpo_groups_share_a_prompt_and_fit_no_value_function():
    torch.manual_seed(0)
    sft, reward_model = rlhf.TinyLM(16, 1, 2), rlhf.TinyLM(16, 1, 2)
    args = rlhf.Args(response_length=12, batch_size=16, advantage="grpo", group_size=4)
    agent = rlhf.Agent(sft, reward_model, "policy-head")
    batch = rlhf.rollout(agent, sft, reward_model, args)
    prompts = batch["tokens"][:, : rlhf.PROMPT_LENGTH].view(4, 4, -1)
    assert torch.equal(prompts, prompts[:, :1].expand_as(prompts)), "a group answers one prompt"
    assert len({tuple(p) for p in prompts[:, 0].tolist()}) > 1, "the groups' prompts are drawn anew"
    rewards = rlhf.compute_rewards(batch["scores"], batch["logprobs"], batch["ref_logprobs"], batch["mask"], 0.05)
    batch["returns"] = batch["values"] + 100.0  # a value loss would be large: GRPO's loss must not contain it
    sgd = torch.optim.SGD(agent.parameters(), lr=0.0)
    update_stats = rlhf.group_baseline_update(agent, sgd, batch, rewards, args, "cpu")
    torch.testing.assert_close(batch["advantages"], group_advantages(rewards, batch["mask"], 4))
    assert len(update_stats) == args.update_epochs  # one minibatch of the 16 responses an epoch
    for stats in update_stats:
        assert stats["loss"].item() == pytest.approx(stats["policy_loss"].item())
        assert "value_loss" not in stats, "no value function is fitted: no value loss is logged"


def test_losses_are_means_over_the_masked_tokens_only():
    ratio, adv, mask = torch.tensor([1.5, 0.5, 9.0]), torch.tensor([1.0, 1.0, 5.0]), torch.tensor([1.0, 1.0, 0.0])
    assert rlhf.clipped_surrogate_loss(ratio, adv, 0.2, mask).item() == pytest.approx(-(1.2 + 0.5) / 2)
    new, old, ret = torch.tensor([1.0, 3.0, 50.0]), torch.zeros(3), torch.tensor([0.0, 1.0, 0.0])
    assert rlhf.value_loss(new, old, ret, 10.0, mask).item() == pytest.approx((1.0 + 4.0) / 2)


# THE LANGUAGE
def test_the_grammar_is_well_formed_and_the_gold_reward_is_the_valence_sum():
    import random

    rng = random.Random(0)
    reviews = [" ".join(rlhf.sample_review(rng)) for _ in range(2000)]
    assert all(rlhf.parse_review(review) is not None for review in reviews)
    # People never write a clause twice: the corpus has none, so the reward model never sees one ranked.
    clauses = [review.removesuffix(" <eos>").split(" and ") for review in reviews]
    assert all(len(set(c)) == len(c) for c in clauses) and max(map(len, clauses)) == 3
    assert rlhf.parse_review("the film was very superb and the plot was not awful and the cast was dull <eos>") == 8
    # A reader takes a review that repeats a clause word for word for spam; the same aspect judged anew is no repeat.
    assert rlhf.parse_review("the film was superb and the plot was good and the film was superb <eos>") == -6
    assert rlhf.parse_review("the film was superb and the film was very superb <eos>") == 9
    for broken in ["the film was good", "the film was good and <eos>", "the film was very very good <eos>", "<eos>"]:
        assert rlhf.parse_review(broken) is None, broken
    assert len(set(rlhf.WORDS)) == len(rlhf.WORDS) and len({rlhf.PAD, rlhf.BOS, rlhf.EOS}) == 3


def test_preference_pairs_are_two_responses_to_one_prompt_whose_clause_gold_counts(tiny_run):
    _, run_dir = tiny_run
    args = rlhf_tiny_args(run_dir.parent)
    sft = rlhf.new_model(args, "cpu", rlhf.load_checkpoint(str(run_dir / "sft.pt"), args, "sft")[0]["model"])
    tokens, mask, chosen, rejected, n_train = rlhf.preference_pairs(sft, args, "cpu")
    P = rlhf.PROMPT_LENGTH
    assert torch.equal(tokens[chosen, :P], tokens[rejected, :P]), "a pair answers one prompt"
    gold, _ = rlhf.gold_scores(tokens, mask)
    assert (gold[chosen] > gold[rejected]).all() and 0 < n_train < len(chosen)
    prompts = {" ".join(rlhf.WORDS[t] for t in row[1:]) for row in tokens[:, :P].tolist()}
    assert len(prompts) > 10 and all(re.fullmatch(rf"{rlhf.CLAUSE} and", p) for p in prompts), prompts
    # The same response after a good and a bad first clause: the reader counts the prompt's clause
    gold, _ = rlhf.gold_scores(
        *tokens_of("the film was superb and the plot was good <eos>", "the film was awful and the plot was good <eos>")
    )
    assert gold.tolist() == [5.0, -1.0]


def test_generation_masks_and_pads_after_the_first_eos():
    torch.manual_seed(0)
    lm = rlhf.TinyLM(16, 1, 2)
    tokens, mask = rlhf.generate(lm, 32, 10, 1.0)
    responses = tokens[:, rlhf.PROMPT_LENGTH :]
    assert tokens.shape == (32, rlhf.PROMPT_LENGTH + 10) and mask.shape == (32, 10)
    for row, m in zip(responses.tolist(), mask.tolist(), strict=True):
        end = row.index(rlhf.EOS) + 1 if rlhf.EOS in row else len(row)
        assert m == [1.0] * end + [0.0] * (len(row) - end)
        assert all(t == rlhf.PAD for t in row[end:])


# THE PPO UPDATE
def a_batch(value_model="reward-model", seed=0):
    torch.manual_seed(seed)
    sft = rlhf.TinyLM(16, 1, 2)
    reward_model = rlhf.TinyLM(16, 1, 2)
    agent = rlhf.Agent(sft, reward_model, value_model)
    args = rlhf.Args(response_length=12, batch_size=16)
    batch = rlhf.rollout(agent, sft, reward_model, args)
    rewards = rlhf.compute_rewards(batch["scores"], batch["logprobs"], batch["ref_logprobs"], batch["mask"], 0.05)
    batch["advantages"], batch["returns"] = rlhf.compute_gae(rewards, batch["values"], batch["mask"], 1.0, 0.95)
    return agent, batch, args


@pytest.mark.parametrize("value_model", ["reward-model", "policy-head"])
def test_ratio_is_one_and_approx_kl_zero_on_the_first_minibatch(value_model):
    agent, batch, args = a_batch(value_model)
    mb = {k: v[:8] for k, v in batch.items()}
    logits, _ = agent(mb["tokens"])
    newlogprobs = rlhf.response_dist(logits, args.temperature).log_prob(mb["responses"])
    ratio = ((newlogprobs - mb["logprobs"]) * mb["mask"]).exp()
    torch.testing.assert_close(ratio, torch.ones_like(ratio), atol=1e-5, rtol=0)
    stats = rlhf.ppo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)
    assert abs(stats["approx_kl"].item()) < 1e-8 and abs(stats["old_approx_kl"].item()) < 1e-5
    assert stats["clipfrac"].item() == 0.0


def gradients(agent, mb, args):
    rlhf.ppo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)  # lr 0: the weights stay
    return {name: p.grad.clone() for name, p in agent.named_parameters() if p.grad is not None}


def test_masked_positions_change_no_gradient():
    agent, batch, args = a_batch()
    mask = batch["mask"]
    assert (mask == 0).any(), "the batch has positions after an EOS"
    before = gradients(agent, batch, args)
    garbage = dict(batch)
    after_the_end = mask == 0
    garbage["responses"] = batch["responses"].masked_fill(after_the_end, rlhf.TOKEN["superb"])
    garbage["tokens"] = torch.cat([batch["tokens"][:, : rlhf.PROMPT_LENGTH], garbage["responses"]], 1)
    for key in ("logprobs", "values", "returns", "advantages"):
        garbage[key] = torch.where(after_the_end, torch.full_like(batch[key], 1e4), batch[key])
    after = gradients(agent, garbage, args)
    assert before.keys() == after.keys() and before
    for name in before:
        torch.testing.assert_close(before[name], after[name], msg=name)


# THE COMMAND LINE
def test_tiny_run_logs_and_checkpoints_each_stage(tiny_run, tmp_path):
    _, run_dir = tiny_run
    for name, stage in [("sft.pt", "sft"), ("reward_model.pt", "reward_model"), ("checkpoint.pt", "ppo")]:
        checkpoint = torch.load(run_dir / name, weights_only=True)
        assert checkpoint["format"] == "ppo-checkpoint-v1" and checkpoint["stage"] == stage
    checkpoint = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert checkpoint["global_step"] == 64 and checkpoint["iteration"] == 4 and checkpoint["optimizer"]["state"]
    scalars = tb_scalars(run_dir)
    rlhf_names = ["score", "gold_score", "kl", "kl_coef", "entropy", "response_length", "eos_fraction"]
    losses = ["policy_loss", "value_loss", "entropy", "approx_kl", "old_approx_kl", "clipfrac", "explained_variance"]
    expected = {f"rlhf/{n}" for n in rlhf_names} | {f"losses/{n}" for n in losses}
    assert expected | {"charts/episodic_return", "charts/SPS"} <= set(scalars)
    assert [step for step, _ in scalars["charts/SPS"]] == [16, 32, 48, 64]
    assert not list(run_dir.glob("*.tmp"))


def test_train_restores_signal_handlers_and_threads_even_when_it_fails(tmp_path, monkeypatch):
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    threads = torch.get_num_threads()
    monkeypatch.setattr(rlhf, "clipped_surrogate_loss", lambda *a, **k: torch.tensor(float("nan"), requires_grad=True))
    with pytest.raises(
        rlhf.Diverged, match="not finite after iteration 1; start a new run with a smaller --learning-rate"
    ):
        rlhf.train(rlhf_tiny_args(tmp_path, torch_threads=threads + 1))
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers and torch.get_num_threads() == threads


def test_same_seed_same_run_and_cached_stages_change_nothing(tiny_run, tmp_path):
    agent, run_dir = tiny_run
    again, _ = rlhf.train(rlhf_tiny_args(tmp_path, "again"))
    stages = {"sft_checkpoint": str(run_dir / "sft.pt"), "reward_model_checkpoint": str(run_dir / "reward_model.pt")}
    cached, _ = rlhf.train(rlhf_tiny_args(tmp_path, "cached", **stages))
    other, _ = rlhf.train(rlhf_tiny_args(tmp_path, "other", seed=2))
    for name, weight in agent.state_dict().items():
        assert torch.equal(weight, again.state_dict()[name]), name
        assert torch.equal(weight, cached.state_dict()[name]), name
    assert not torch.equal(agent.state_dict()["policy.tok_emb.weight"], other.state_dict()["policy.tok_emb.weight"])
    assert not (tmp_path / "cached" / "sft.pt").exists(), "a cached stage is not run again"


def test_ctrl_c_saves_and_resume_continues_the_curve(tmp_path):
    run_dir = tmp_path / "run"
    flags = [*TINY_FLAGS, "--total-episodes", "640", "--save-every", "1", "--run-dir", run_dir, *ONE_THREAD]
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / SCRIPT), *map(str, flags)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    out, err = signal_at_checkpoint(proc, run_dir / "checkpoint.pt", signal.SIGINT, wait=120)
    assert proc.returncode == 130 and "Traceback" not in err and "--resume" in out, (out, err)
    stopped_at = torch.load(run_dir / "checkpoint.pt", weights_only=True)["global_step"]
    assert 0 < stopped_at < 640
    resumed = run_cli(SCRIPT, "--resume", run_dir / "checkpoint.pt", cwd=tmp_path)
    assert f"at step {stopped_at:,}" in resumed.stdout
    assert torch.load(run_dir / "checkpoint.pt", weights_only=True)["global_step"] == 640
    assert [step for step, _ in tb_scalars(run_dir)["charts/SPS"]] == list(range(16, 641, 16))


def test_divergence_is_one_line_and_exit_1(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(rlhf, "clipped_surrogate_loss", lambda *a, **k: torch.tensor(float("nan"), requires_grad=True))
    monkeypatch.setattr(sys, "argv", [SCRIPT, *TINY_FLAGS, "--run-dir", str(tmp_path / "run"), *ONE_THREAD])
    with pytest.raises(SystemExit) as stopped:
        rlhf.main()
    err = capsys.readouterr().err.strip().splitlines()
    assert stopped.value.code == 1 and len(err) == 1 and "not finite after iteration 1" in err[0], err
    assert "start a new run with a smaller --learning-rate" in err[0], err  # as --resume refuses a typed one


def bad_input_files(tmp_path):
    (tmp_path / "afile").write_text("")
    (tmp_path / "corrupt.pt").write_bytes(b"\x80\x02not a checkpoint")
    (tmp_path / "oldrun").mkdir()
    (tmp_path / "oldrun" / "sft.pt").write_bytes(b"")
    torch.save({"format": "ppo-checkpoint-v1", "script": "ppo_continuous.py"}, tmp_path / "foreign.pt")
    small = rlhf.TinyLM(16, 1, 2)
    args = rlhf.Args(d_model=16, n_layer=1, n_head=2)
    rlhf.save_checkpoint(str(tmp_path / "sft.pt"), "sft", args, model=small.state_dict())


BAD_INPUTS = [
    (["--learning-rate", "nan"], "--learning-rate must be a finite number, got nan"),
    (["--kl-coef", "inf"], "--kl-coef must be a finite number"),
    (["--kl-coef", "-0.1"], "--kl-coef must be in [0, inf]"),
    (["--gamma", "1.5"], "--gamma must be in [0, 1]"),
    (["--temperature", "0"], "--temperature must be positive"),
    (["--total-episodes", "0"], "--total-episodes must be positive"),
    (["--total-episodes", "32"], "less than one batch of 64"),
    (["--minibatch-size", "48"], "--minibatch-size 48 does not divide --batch-size 64"),
    (["--n-head", "3"], "--n-head 3 does not divide --d-model 64"),
    (["--response-length", "27"], "--response-length must be in [5, 26]"),
    (["--response-length", "1"], "--response-length must be in [5, 26]"),
    (["--rm-pairs", "2"], "--rm-pairs must be in [100, inf]"),
    (["--adaptive-kl", "--kl-coef", "0"], "--adaptive-kl needs a positive --kl-coef"),
    (["--advantage", "grpo", "--group-size", "7"], "--group-size 7 does not divide --batch-size 64"),
    (["--advantage", "grpo", "--group-size", "1"], "--group-size must be in [2, inf]"),
    (["--dpo", "--kl-coef", "0"], "--dpo and --kto take their beta from a positive, fixed --kl-coef"),
    (["--kto", "--advantage", "rloo"], "--dpo and --kto take their beta from a positive, fixed --kl-coef, and have no"),
    (["--dpo", "--kto"], "--dpo and --kto are two losses of stage 3: take one"),
    (["--kto", "--kto-weights", "1", "nan"], "--kto-weights must be two positive numbers, got (1.0, nan)"),
    (["--kto", "--kto-desirable-share", "1.5"], "--kto-desirable-share must be in [0, 1]"),
    (["--rm-ensemble", "0"], "--rm-ensemble must be positive"),
    (["--rm-same-head"], "--rm-same-head is how the members of an ensemble start: add --rm-ensemble K > 1"),
    (["--reward", "process", "--rm-ensemble", "2"], "--reward process trains one process reward model: drop"),
    (["--reward", "steps"], "invalid choice"),
    (["--rm-refresh", "-1"], "--rm-refresh must be in [0, inf]"),
    (["--rm-refresh", "4", "--rm-ensemble", "2"], "--rm-refresh trains the one reward model PPO reads: drop"),
    (["--rm-refresh", "4", "--dpo", "--kl-coef", "0.1"], "--rm-refresh trains the one reward model PPO reads: drop"),
    (["--rm-ensemble", "2", "--uwo-coef", "-1"], "--uwo-coef must be in [0, inf]"),
    (["--rm-ensemble-agg", "max"], "invalid choice"),
    (["--ipo"], "--ipo is a loss of --dpo: add --dpo"),
    (["--value-model", "both"], "invalid choice"),
    (["--device", "tpu"], "--device tpu is not available"),
    (["--run-dir", "afile"], "is a file"),
    (["--run-dir", "afile/run"], "cannot be created or written"),
    (["--run-dir", "oldrun"], "already holds a run: continue it with --resume oldrun/checkpoint.pt"),
    (["--resume", "missing.pt"], "does not exist"),
    (["--resume", "corrupt.pt"], "corrupt"),
    (["--resume", "foreign.pt"], "not a checkpoint written by ppo_rlhf.py"),
    (["--resume", "sft.pt"], "a checkpoint of the sft stage, not of the ppo stage"),
    (["--reward-model-checkpoint", "sft.pt"], "not of the reward_model stage"),
    (["--sft-checkpoint", "sft.pt"], "'sft.pt' holds another network: tok_emb.weight"),
]


@pytest.mark.parametrize("args,message", BAD_INPUTS, ids=[m for _, m in BAD_INPUTS])
def test_bad_input_is_one_line_before_anything_starts(tmp_path, args, message, monkeypatch, capsys):
    bad_input_files(tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", [SCRIPT, *args])
    monkeypatch.setattr(rlhf, "train", lambda args: pytest.fail("training started"))
    with pytest.raises(SystemExit) as stopped:
        rlhf.main()
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert stopped.value.code == 2, err
    if message != "invalid choice":  # tyro's own message for a choice it does not know is a box of lines
        assert len(lines) == 1 and "error:" in lines[0] and message in lines[0], err
    assert message in err
    assert not (tmp_path / "runs").exists()


def test_bad_flag_from_the_shell_is_one_line_and_exit_2(tmp_path):
    proc = run_cli(SCRIPT, "--gamma", "nan", cwd=tmp_path, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "--gamma must be a finite number" in lines[0], proc.stderr
    assert not (tmp_path / "runs").exists()


# PPO's successors on the same axes: three group baselines, the hack by name, and what a stop leaves.
def reference_group_baseline(returns, group_size, kind):
    """Each response's advantage from its group, by a plain loop over the responses."""
    out = np.zeros(len(returns))
    for start in range(0, len(returns), group_size):
        group = returns[start : start + group_size]
        for i, r in enumerate(group):
            others = np.delete(group, i)
            if kind == "rloo":
                out[start + i] = r - others.mean()
            elif kind == "dr-grpo":
                out[start + i] = r - group.mean()
            else:
                out[start + i] = (r - group.mean()) / (group.std(ddof=1) + 1e-8)
    return out


@pytest.mark.parametrize("kind", ["grpo", "dr-grpo", "rloo"])
def test_group_baselines_match_a_loop_over_responses(kind):
    rng = np.random.default_rng(7)
    mask = masks_with_a_row_without_eos(rng, 8, 6)
    rewards = rng.normal(size=(8, 6)) * mask
    advantages = group_advantages(*t64(rewards, mask), 4, kind).numpy()
    expected = reference_group_baseline(rewards.sum(1), 4, kind)[:, None] * mask
    np.testing.assert_allclose(advantages, expected, atol=1e-9)


def test_rloo_is_dr_grpo_scaled_by_k_over_k_minus_1():
    rewards, mask = torch.randn(12, 1, dtype=torch.float64), torch.ones(12, 1, dtype=torch.float64)
    rloo = group_advantages(rewards, mask, 4, "rloo")
    assert torch.allclose(rloo, 4 / 3 * group_advantages(rewards, mask, 4, "dr-grpo"))


def test_grpos_division_makes_its_beta_beta_over_the_groups_std():
    """With the KL penalty in the reward, GRPO's advantage is Dr. GRPO's with the score and beta both divided by the
    std of the group's summed rewards: the penalty's weight differs from group to group."""
    rng = np.random.default_rng(3)
    scores, logprobs, ref_logprobs = t64(rng.normal(size=4), rng.normal(size=(4, 5)), rng.normal(size=(4, 5)))
    mask, beta = torch.ones(4, 5, dtype=torch.float64), 0.05
    rewards = rlhf.compute_rewards(scores, logprobs, ref_logprobs, mask, beta)
    sigma = rewards.sum(1).std()
    grpo = group_advantages(rewards, mask, 4, "grpo")
    rescaled = rlhf.compute_rewards(scores / sigma, logprobs, ref_logprobs, mask, beta / sigma)
    assert torch.allclose(grpo, group_advantages(rescaled, mask, 4, "dr-grpo"), atol=1e-7)


def tokens_of(*texts):
    """Sequences [B, T] and response masks of texts "the NOUN was ADJ and ...": the prompt is their first clause."""
    rows = [[rlhf.BOS] + [rlhf.TOKEN[w] for w in text.split()] for text in texts]
    width = max(map(len, rows))
    tokens = torch.tensor([row + [rlhf.PAD] * (width - len(row)) for row in rows])
    mask = torch.tensor([[1.0] * (len(row) - rlhf.PROMPT_LENGTH) + [0.0] * (width - len(row)) for row in rows])
    return tokens, mask


def test_each_response_has_one_form_and_spam_is_not_well_formed():
    texts = [
        "the film was good and the plot was fine <eos>",
        "the film was awful and the plot was bad and the cast was dull <eos>",  # well formed, and as bad as spam
        "the film was good and the film was good <eos>",
        "the film was good and was good <eos>",
    ]
    gold, forms = rlhf.gold_scores(*tokens_of(*texts))
    assert gold.tolist() == [3.0, -6.0, -6.0, -6.0]
    assert forms["well_formed"].tolist() == [1, 1, 0, 0]
    assert forms["spam"].tolist() == [0, 0, 1, 0]
    assert forms["garbled"].tolist() == [0, 0, 0, 1]


def test_rm_accuracy_rests_on_the_recent_pool_and_a_collapsed_batch_leaves_it_defined():
    tokens, mask = tokens_of(*["the film was good and the film was good <eos>"] * 4)  # collapsed onto one spam text
    gold, forms = rlhf.gold_scores(tokens, mask)
    zeros = torch.zeros_like(mask)
    batch = {"scores": torch.full((4,), 2.0), "gold": gold, "mask": mask, "logprobs": zeros, "ref_logprobs": zeros}
    batch |= forms | {"entropy": zeros, "has_eos": torch.ones(4)}
    prompt = torch.full((4,), 7.0)
    assert math.isnan(rlhf.pairwise_accuracy(batch["scores"], batch["gold"], prompt)[0]), "the batch alone: no pair"
    # (RM score, gold, prompt) of earlier responses: two to prompt 7, one to prompt 8
    earlier = torch.tensor([[0.5, 1.0, 1.5], [9.0, 2.0, 4.0], [7.0, 7.0, 8.0]])
    pool = torch.cat([earlier, torch.stack([batch["scores"], batch["gold"], prompt])], 1)
    stats = rlhf.response_stats(batch, pool)
    # pairs to prompt 7 of different gold: 9 > 2 among the earlier (the RM gets it wrong, 0.5 < 1.0), and each of those
    # two above the 4 spam copies (-6) (8 pairs, the RM gets none right: 2.0 beats them both); prompt 8 has one response
    assert stats["rlhf/rm_pairs"] == 9 and stats["rlhf/rm_accuracy"] == 0
    assert stats["rlhf/spam"] == 1 and stats["rlhf/well_formed"] == 0


def test_a_stop_in_stage_1_says_that_nothing_is_saved(tmp_path):
    with pytest.raises(rlhf.Stopped, match="stage 1, SFT at step 1; nothing is saved yet"):
        rlhf.train(rlhf_tiny_args(tmp_path), stop=[signal.SIGINT])
    assert not list((tmp_path / "run").glob("*.pt"))


def test_a_stop_in_stage_2_points_to_the_saved_stage_1(tmp_path):
    class AfterStage1:  # the stop flag, raised once stage 1 is on disk
        def __bool__(self):
            return (tmp_path / "run" / "sft.pt").exists()

    with pytest.raises(rlhf.Stopped, match="stage 2, reward model at step 1; stage 1 is saved: go on with") as e:
        rlhf.train(rlhf_tiny_args(tmp_path), stop=AfterStage1())
    path = str(e.value).split("--sft-checkpoint ")[1]
    assert rlhf.load_checkpoint(path, rlhf.Args(), "sft")[0]["stage"] == "sft"


@pytest.mark.parametrize("advantage", ["dr-grpo", "rloo"])
def test_group_baselines_run_from_the_command_line(advantage, tmp_path):
    run_cli(SCRIPT, *TINY_FLAGS, "--advantage", advantage, "--group-size", "4", "--run-dir", "run", cwd=tmp_path)
    scalars = tb_scalars(tmp_path / "run")
    assert "losses/value_loss" not in scalars and "losses/policy_loss" in scalars
    assert {"rlhf/spam", "rlhf/garbled", "rlhf/rm_pairs"} <= set(scalars)
    assert all(math.isfinite(value) for _, value in scalars["rlhf/rm_accuracy"])


def test_sequence_logprobs_sum_each_responses_token_log_probs():
    torch.manual_seed(0)
    lm = rlhf.TinyLM(16, 1, 2)
    tokens, mask = tokens_of(
        "the film was good and the set was dull <eos>", "the plot was bad and the cast was fine <eos>"
    )
    logits = lm(tokens)[0].double()
    expected = []
    for i in range(2):
        total = 0.0
        for t in range(int(mask[i].sum())):  # position P - 1 + t predicts response token t
            total += torch.log_softmax(logits[i, rlhf.PROMPT_LENGTH - 1 + t], -1)[tokens[i, rlhf.PROMPT_LENGTH + t]]
        expected.append(total.item())
    assert rlhf.sequence_logprobs(lm, tokens, mask, 1.0).tolist() == pytest.approx(expected, abs=1e-5)


def moved_policy_and_pair():
    """An agent whose policy has moved away from pi_SFT (another random init), and a minibatch of one preference pair
    with pi_SFT's log-prob of each response, as dpo_update takes it."""
    torch.manual_seed(1)
    sft, moved = rlhf.TinyLM(16, 1, 2), rlhf.TinyLM(16, 1, 2)
    agent = rlhf.Agent(moved, moved, "policy-head")
    chosen, chosen_mask = tokens_of("the film was fine and the plot was superb <eos>")
    rejected, rejected_mask = tokens_of("the film was fine and the plot was awful <eos>")
    mb = {"chosen_tokens": chosen, "chosen_mask": chosen_mask, "rejected_tokens": rejected}
    mb |= {"rejected_mask": rejected_mask}
    mb |= {
        f"{side}_ref": rlhf.sequence_logprobs(sft, mb[f"{side}_tokens"], mb[f"{side}_mask"], 1.0).detach()
        for side in ("chosen", "rejected")
    }
    return agent, mb


def log_ratio_margin(lm, mb):
    """(log pi - log pi_SFT)(y_w) - (log pi - log pi_SFT)(y_l), by hand."""
    return sum(
        sign * (rlhf.sequence_logprobs(lm, mb[f"{side}_tokens"], mb[f"{side}_mask"], 1.0) - mb[f"{side}_ref"])
        for sign, side in ((1, "chosen"), (-1, "rejected"))
    ).item()


def test_dpo_is_the_reward_models_loss_on_the_implicit_reward():
    """-log sigmoid(beta ((log pi - log pi_SFT)(y_w) - (log pi - log pi_SFT)(y_l))), by hand, on a policy that has
    moved away from pi_SFT; and a step of it raises pi's preference for the chosen response."""
    agent, mb = moved_policy_and_pair()
    args = rlhf.Args(kl_coef=0.5)
    margin = log_ratio_margin(agent.policy, mb)
    stats = rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)
    assert stats["loss"].item() == pytest.approx(math.log(1 + math.exp(-0.5 * margin)), rel=1e-5)
    before = stats["loss"].item()
    rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.1), mb, args)
    after = rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)["loss"].item()
    assert after < before


def test_ipo_is_the_squared_distance_of_the_log_ratio_margin_from_its_target():
    """Azar et al. 2023's IPO loss, (h - 1 / (2 tau))^2 with h = log(pi(y_w) pi_SFT(y_l) / (pi(y_l) pi_SFT(y_w))), by
    hand, at tau = --kl-coef, on a policy that has moved away from pi_SFT; and a step of it moves the margin toward
    1 / (2 tau)."""
    agent, mb = moved_policy_and_pair()
    for tau in (0.5, 0.1):
        args = rlhf.Args(kl_coef=tau, dpo=True, ipo=True)
        h = log_ratio_margin(agent.policy, mb)
        stats = rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)
        assert stats["loss"].item() == pytest.approx((h - 1 / (2 * tau)) ** 2, rel=1e-5)
        rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.1), mb, args)
        assert abs(log_ratio_margin(agent.policy, mb) - 1 / (2 * tau)) < abs(h - 1 / (2 * tau))


def kto_by_hand(agent, mb, beta, weights, kept):
    """KTO's loss from its definition: each response's implied reward r = beta (log pi - log pi_SFT), the reference
    point z0 = max(0, that of the mismatched pair), and lambda (1 - sigmoid(+-(r - z0))) averaged over the responses
    kept."""
    r = {
        side: beta
        * (rlhf.sequence_logprobs(agent.policy, mb[f"{side}_tokens"], mb[f"{side}_mask"], 1.0) - mb[f"{side}_ref"])
        for side in ("chosen", "rejected", "kl")
    }
    z0 = max(0.0, r["kl"].item())
    losses = [weights[1] * (1 - 1 / (1 + math.exp(-(z0 - r["rejected"].item()))))]
    if kept:
        losses.append(weights[0] * (1 - 1 / (1 + math.exp(-(r["chosen"].item() - z0)))))
    return sum(losses) / len(losses)


@pytest.mark.parametrize("kept", [True, False])
def test_kto_judges_each_response_alone_against_the_reference_point(kept):
    """Ethayarajh et al. 2024's loss by hand, with lambda_D 1 and lambda_U 2, on a policy that has moved away from
    pi_SFT, whose mismatched pair (the rejected response after the chosen one's prompt) sets z0; without the chosen
    response (--kto-desirable-share), the rejected one's term alone. A step lowers it, and z0 takes no gradient."""
    agent, mb = moved_policy_and_pair()
    mismatched, kl_mask = tokens_of("the plot was bad and the cast was fine <eos>")
    mismatched[:, : rlhf.PROMPT_LENGTH] = mb["chosen_tokens"][:, : rlhf.PROMPT_LENGTH]
    torch.manual_seed(1)
    sft = rlhf.TinyLM(16, 1, 2)  # moved_policy_and_pair's pi_SFT: the first of its two draws
    mb |= {"kl_tokens": mismatched, "kl_mask": kl_mask, "kept": torch.tensor([kept])}
    mb["kl_ref"] = rlhf.sequence_logprobs(sft, mismatched, kl_mask, 1.0).detach()
    args = rlhf.Args(kl_coef=0.5, kto=True, kto_weights=(1.0, 2.0))
    expected = kto_by_hand(agent, mb, 0.5, (1.0, 2.0), kept)
    stats = rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)
    assert stats["loss"].item() == pytest.approx(expected, rel=1e-5)
    rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.1), mb, args)
    assert rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)["loss"] < stats["loss"]


def test_kto_mismatched_pairs_are_the_minibatchs_own_responses_each_after_another_prompt(tiny_run):
    """KTO's KL batch, built for each minibatch as TRL's KTOTrainer builds it: the kept chosen responses, then the
    rejected ones, each after the prompt of the one that follows it in that list, with pi_SFT's log-prob; and dpo_pairs
    keeps the first --kto-desirable-share of the pairs' chosen responses."""
    _, run_dir = tiny_run
    args = rlhf.Args(**{**vars(rlhf_tiny_args(run_dir.parent)), "kto": True, "kto_desirable_share": 0.25})
    sft = rlhf.new_model(args, "cpu", torch.load(run_dir / "sft.pt", weights_only=True)["model"])
    pairs = rlhf.dpo_pairs(sft, args, "cpu")
    n = len(pairs["kept"])
    assert pairs["kept"].tolist() == [i < 0.25 * n for i in range(n)]
    rows = torch.tensor([0, n - 1, 1, n - 2, 2, n // 2])  # kept and not kept, mixed
    mb = {key: value[rows] for key, value in pairs.items()}
    mb = rlhf.kto_mismatched(sft, mb, args)
    P = rlhf.PROMPT_LENGTH
    kept = [i for i in range(len(rows)) if mb["kept"][i]]
    assert 0 < len(kept) < len(rows)
    own = [(mb["chosen_tokens"][i], mb["chosen_mask"][i]) for i in kept]
    own += [(mb["rejected_tokens"][i], mb["rejected_mask"][i]) for i in range(len(rows))]
    assert len(mb["kl_tokens"]) == len(own)
    for j, (tokens, _) in enumerate(own):  # row j: its own prompt, and the response of row j - 1
        previous_tokens, previous_mask = own[j - 1]
        assert torch.equal(mb["kl_tokens"][j, :P], tokens[:P])
        assert torch.equal(mb["kl_tokens"][j, P:], previous_tokens[P:])
        assert torch.equal(mb["kl_mask"][j], previous_mask)
    ref = rlhf.sequence_logprobs(sft, mb["kl_tokens"], mb["kl_mask"], 1.0)
    torch.testing.assert_close(mb["kl_ref"], ref)


def test_kto_holds_its_reference_point_constant_where_it_is_positive():
    """z0 = max(0, the mismatched pairs' mean implied reward) is a constant of KTO's gradient, as in TRL. Here it is
    positive (0.5), so the clamp passes a gradient: dpo_update's gradient must be that of the loss with z0 detached,
    and differ from the loss with z0 live. The logged z0 and the mean it clamps are the values by hand."""
    agent, mb = moved_policy_and_pair()
    mismatched, kl_mask = tokens_of("the plot was bad and the cast was fine <eos>")
    mismatched[:, : rlhf.PROMPT_LENGTH] = mb["chosen_tokens"][:, : rlhf.PROMPT_LENGTH]
    with torch.no_grad():  # pi_SFT's log-prob set 1 nat below pi's: the implied reward is beta x 1 = 0.5
        kl_ref = rlhf.sequence_logprobs(agent.policy, mismatched, kl_mask, 1.0) - 1.0
    mb |= {"kl_tokens": mismatched, "kl_mask": kl_mask, "kl_ref": kl_ref, "kept": torch.tensor([True])}
    args = rlhf.Args(kl_coef=0.5, kto=True, kto_weights=(1.0, 2.0), max_grad_norm=1e9)  # no clipping of the norm

    def gradient(z0_is_constant):
        r = {
            side: 0.5
            * (rlhf.sequence_logprobs(agent.policy, mb[f"{side}_tokens"], mb[f"{side}_mask"], 1.0) - mb[f"{side}_ref"])
            for side in ("chosen", "rejected", "kl")
        }
        z0 = r["kl"].mean().clamp(min=0)
        z0 = z0.detach() if z0_is_constant else z0
        loss = (1.0 * (1 - torch.sigmoid(r["chosen"] - z0)) + 2.0 * (1 - torch.sigmoid(z0 - r["rejected"]))) / 2
        return torch.autograd.grad(loss.sum(), list(agent.policy.parameters()), allow_unused=True)

    constant, live = gradient(True), gradient(False)
    stats = rlhf.dpo_update(agent, torch.optim.SGD(agent.parameters(), lr=0.0), mb, args)
    assert stats["kto_z0"].item() == pytest.approx(0.5, rel=1e-4)
    assert stats["kto_mismatched_reward"].item() == pytest.approx(0.5, rel=1e-4)
    seen = [p.grad for p in agent.policy.parameters()]
    differs = False
    for g, c, lv in zip(seen, constant, live, strict=True):
        if c is None:
            continue
        torch.testing.assert_close(g, c, rtol=1e-4, atol=1e-7)
        differs |= not torch.allclose(c, lv, rtol=1e-3, atol=1e-6)
    assert differs  # the test can tell the two apart


def test_every_member_of_an_ensemble_has_its_own_data_order_and_head(tiny_run, tmp_path, monkeypatch):
    """--rm-ensemble 4: each member's first epoch visits the pairs in an order of its own, and its score head starts
    from weights of its own, not zeros. With --rm-same-head, and for a single reward model, every head starts at 0."""
    _, run_dir = tiny_run
    heads, orders = [], []
    fit, randperm = rlhf.fit, torch.randperm

    def fit_seen(model, *rest):
        heads.append(torch.cat([model.score_head.weight.flatten(), model.score_head.bias]).clone())
        return fit(model, *rest)

    def randperm_seen(n, *rest, **kwargs):
        perm = randperm(n, *rest, **kwargs)
        orders.append(perm.clone())
        return perm

    monkeypatch.setattr(rlhf, "fit", fit_seen)
    monkeypatch.setattr(torch, "randperm", randperm_seen)
    for members, same_head in ((4, False), (4, True), (1, False)):
        heads.clear()
        orders.clear()
        args = rlhf_tiny_args(tmp_path, f"k{members}{same_head}", rm_ensemble=members, rm_same_head=same_head)
        rlhf.train(rlhf.Args(**{**vars(args), "total_episodes": 16, "sft_checkpoint": str(run_dir / "sft.pt")}))
        firsts = orders[: members * args.rm_epochs : args.rm_epochs]  # each member's first epoch (rm_epochs each)
        assert len(heads) == members and len(firsts) == members
        own_heads = members > 1 and not same_head
        for a in range(members):
            assert (torch.count_nonzero(heads[a]) > 0) == own_heads, a
            for b in range(a):
                assert not torch.equal(firsts[a], firsts[b]), (a, b)
                assert torch.equal(heads[a], heads[b]) != own_heads, (a, b)


def watch(monkeypatch, seen, name, record):
    """Replace rlhf.<name> by itself, appending record(its positional arguments, its result) to `seen` at each call."""
    original = getattr(rlhf, name)

    def watched(*call):
        result = original(*call)
        seen.append(record(call, result))
        return result

    monkeypatch.setattr(rlhf, name, watched)


def test_each_ensemble_aggregate_is_the_reward_ppo_learns_from(tiny_run, tmp_path, monkeypatch):
    """--rm-ensemble 3: the scores that compute_rewards turns into PPO's rewards are the members' mean, minimum, or
    mean - lambda x variance (over members, K - 1 in the denominator), computed here from each member's own score."""
    _, run_dir = tiny_run
    seen = []
    watch(monkeypatch, seen, "rollout", lambda call, batch: (call[2], batch))  # (the reward model, the batch)
    watch(monkeypatch, seen, "compute_rewards", lambda call, rewards: call[0])  # the scores
    for aggregate in ("mean", "min", "uwo"):
        seen.clear()
        args = rlhf_tiny_args(tmp_path, aggregate, rm_ensemble=3, rm_ensemble_agg=aggregate, uwo_coef=0.7)
        rlhf.train(rlhf.Args(**{**vars(args), "sft_checkpoint": str(run_dir / "sft.pt")}))
        (ensemble, batch), scores = seen[0], seen[1]  # the first iteration's rollout, and the scores of its rewards
        members = np.array([m.score(batch["tokens"], batch["mask"]).tolist() for m in ensemble])
        assert len(members) == 3 and not np.allclose(members[0], members[1])  # three reward models, not one
        by_hand = {
            "mean": members.mean(0),
            "min": members.min(0),
            "uwo": members.mean(0) - 0.7 * members.var(0, ddof=1),
        }
        expected = np.where(batch["has_eos"].numpy() > 0, by_hand[aggregate], args.no_eos_score)
        np.testing.assert_allclose(scores.numpy(), expected, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(batch["rm_members"].numpy(), members.T, rtol=1e-6)


@pytest.mark.parametrize("method", ["DPO", "KTO"])
def test_dpo_runs_from_the_command_line_and_measures_fresh_samples(method, tmp_path):
    flag = f"--{method.lower()}"
    out = run_cli(SCRIPT, *TINY_FLAGS, flag, "--kl-coef", "0.1", "--run-dir", "run", cwd=tmp_path).stdout
    assert f"stage 3, {method}: iteration 4/4" in out
    scalars = tb_scalars(tmp_path / "run")
    assert {"rlhf/score", "rlhf/gold_score", "rlhf/kl", "losses/implicit_accuracy"} <= set(scalars)
    assert "losses/value_loss" not in scalars
    assert ({"losses/kto_z0", "losses/kto_mismatched_reward"} <= set(scalars)) == (method == "KTO")
    # The results folder keeps KTO's z0 per iteration, for the rlhf report's account of it.
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import results

    results.write_run(tmp_path / "results", "reviews__arm__seed1", [], results.read_run(tmp_path / "run"))
    kto = results.read_series(tmp_path / "results", "kto")
    assert list(kto) == ([("arm", 1)] if method == "KTO" else [])
    if kto:
        steps, z0, mismatched = kto["arm", 1].T
        assert steps.tolist() == [16, 32, 48, 64] and (z0 >= 0).all() and (z0 >= mismatched - 1e-6).all()


def whole_and_stopped(tmp_path, flags):
    """A tiny run with these flags to its end in tmp_path/whole, and the same run stopped in tmp_path/cut once its
    first checkpoint is on disk; returns the whole run's agent."""
    whole, _ = rlhf.train(rlhf_tiny_args(tmp_path, "whole", **flags))

    class AtFirstCheckpoint:
        def __bool__(self):
            return (tmp_path / "cut" / "checkpoint.pt").exists()

    with pytest.raises(rlhf.Stopped):
        rlhf.train(rlhf_tiny_args(tmp_path, "cut", **flags), AtFirstCheckpoint())
    return whole


def test_a_stopped_dpo_run_resumes_bit_for_bit(tmp_path):
    """DPO's pairs are drawn with stage 2's seed before stage 3's random state is set or restored: a run stopped at its
    first checkpoint and resumed ends where an uninterrupted one does; also from a checkpoint whose RM-accuracy pool
    has no prompts, as before the accuracy counted pairs to one prompt."""
    flags = {"dpo": True, "kl_coef": 0.1, "save_every": 2}
    whole = whole_and_stopped(tmp_path, flags)
    checkpoint = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)
    assert checkpoint["iteration"] == 2 and checkpoint["rm_pool"].shape[0] == 3
    torch.save(checkpoint | {"rm_pool": checkpoint["rm_pool"][:2]}, tmp_path / "cut" / "checkpoint.pt")  # (score, gold)
    resumed, _ = rlhf.train(rlhf_tiny_args(tmp_path, "cut", resume=str(tmp_path / "cut" / "checkpoint.pt"), **flags))
    assert all(
        torch.equal(a, b) for a, b in zip(whole.state_dict().values(), resumed.state_dict().values(), strict=True)
    )


# PROCESS SUPERVISION (--reward process): per-clause labels, a reward at each clause's closing token
def test_clause_golds_label_each_step_at_its_closing_token_by_hand():
    """Each response's steps, closed by "and" or EOS, against values worked out by hand; the prompt's clause is said
    already, so saying it again is spam; a step that is no clause is garbled; nothing else is labelled."""
    texts = {  # the prompt "the film was good and" is every text's first clause; then the labels, step by step
        "the film was good and the plot was very bad <eos>": [-4],  # 2 x -2
        "the film was good and the plot was not dull and the cast was superb <eos>": [1, 3],  # -1 x -1, then 3
        "the film was good and the film was good <eos>": [-6],  # the prompt's clause again: spam
        "the film was good and the plot was fine and the plot was fine <eos>": [1, -6],  # its own clause again
        "the film was good and the plot was <eos>": [-6],  # no clause: garbled
        "the film was good and the cast was awful and and <eos>": [-3, -6, -6],  # empty steps: garbled
        "the film was good and the film was very good <eos>": [4],  # the same aspect judged anew: no repeat
    }
    tokens, mask = tokens_of(*texts)
    labels, ends = rlhf.clause_golds(tokens, mask)
    P = rlhf.PROMPT_LENGTH
    for i, (text, expected) in enumerate(texts.items()):
        response = text.split()[P - 1 :]
        closing = [j for j, word in enumerate(response) if word in ("and", "<eos>")]
        assert ends[i].nonzero().flatten().tolist() == closing, text
        assert labels[i, closing].tolist() == expected, text
        assert labels[i].count_nonzero() == len(expected)


def test_on_well_formed_text_the_steps_and_the_prompts_clause_sum_to_gold():
    """On the grammar's own reviews, the prompt's clause value plus the steps' labels is the gold reward, review by
    review; and on spam or garbled text, some step carries the penalty."""
    import random

    rng = random.Random(1)
    texts = []
    while len(texts) < 300:
        review = " ".join(rlhf.sample_review(rng))
        if review.split()[4] == "and":  # a prompt as the script's: "the NOUN was ADJ and", then a response
            texts.append(review)
    texts += ["the film was good and the film was good <eos>", "the film was good and the plot was <eos>"]
    tokens, mask = tokens_of(*texts)
    labels, _ = rlhf.clause_golds(tokens, mask)
    gold, forms = rlhf.gold_scores(tokens, mask)
    for i, text in enumerate(texts):
        if forms["well_formed"][i]:
            prompt_clause = rlhf.parse_review(" ".join(text.split()[: rlhf.PROMPT_LENGTH - 2]) + " <eos>")
            assert prompt_clause + labels[i].sum().item() == gold[i].item(), text
        else:
            assert rlhf.GOLD_PENALTY in labels[i].tolist(), text
    assert forms["well_formed"][:300].all() and not forms["well_formed"][300:].any()


def test_process_rewards_sit_at_the_clause_closing_tokens_not_summed_at_the_eos(tiny_run, tmp_path, monkeypatch):
    """--reward process at beta 0: the rewards that GAE reads are the process RM's scalar at each "and" and EOS of a
    response, and 0 at every other token; a response that never ends gets --no-eos-score at its last token alone.
    Moved to the EOS, or summed into one, they would differ wherever a response has two clauses or more."""
    _, run_dir = tiny_run
    seen = []
    watch(monkeypatch, seen, "rollout", lambda call, batch: (call[2], batch))  # (the reward model, the batch)
    watch(monkeypatch, seen, "compute_gae", lambda call, advantages: call[0].clone())  # the rewards GAE reads
    args = rlhf_tiny_args(tmp_path, "process", reward="process", kl_coef=0.0, response_length=20)
    rlhf.train(rlhf.Args(**{**vars(args), "sft_checkpoint": str(run_dir / "sft.pt")}))
    (reward_model, batch), rewards = seen[0], seen[1]
    assert isinstance(reward_model, rlhf.ProcessRewardModel)
    P = rlhf.PROMPT_LENGTH
    with torch.no_grad():
        scalars = reward_model(batch["tokens"])[1][:, P:]
    expected = torch.zeros_like(rewards)
    two_clauses = 0
    for i, row in enumerate(batch["tokens"][:, P:].tolist()):
        n = int(batch["mask"][i].sum())
        closing = [j for j in range(n) if row[j] in (rlhf.TOKEN["and"], rlhf.EOS)]
        if rlhf.EOS in row[:n]:
            expected[i, closing] = scalars[i, closing]
            two_clauses += len(closing) >= 2
        else:
            expected[i, n - 1] = args.no_eos_score
    assert two_clauses > 0  # so that rewards moved to the EOS, or summed there, would fail
    torch.testing.assert_close(rewards, expected)
    torch.testing.assert_close(batch["scores"], torch.where(batch["has_eos"] > 0, expected.sum(1), args.no_eos_score))


def test_the_process_rms_held_out_clause_accuracy_is_saved_and_logged(tiny_run, tmp_path):
    """Stage 2 with --reward process saves, beside the pairwise accuracy of its summed scores, the share of the
    held-out pairs' clauses whose score has the sign of their gold, as a loop over those clauses finds it, and the
    labels it learned from; stage 3 logs the same share on the policy's own responses (rlhf/rm_clause_accuracy)."""
    _, run_dir = tiny_run
    args = rlhf_tiny_args(tmp_path, "process", reward="process")
    rlhf.train(rlhf.Args(**{**vars(args), "sft_checkpoint": str(run_dir / "sft.pt")}))
    saved = torch.load(tmp_path / "process" / "reward_model.pt", weights_only=True)
    sft = rlhf.new_model(args, "cpu", torch.load(run_dir / "sft.pt", weights_only=True)["model"])
    prm = rlhf.new_model(args, "cpu", saved["model"], kind=rlhf.ProcessRewardModel)
    tokens, mask, chosen, rejected, n_train = rlhf.preference_pairs(sft, args, "cpu")
    right = total = 0
    P = rlhf.PROMPT_LENGTH
    with torch.no_grad():
        for row in torch.cat([chosen[n_train:], rejected[n_train:]]).tolist():
            words = [rlhf.WORDS[t] for t in tokens[row, : P + int(mask[row].sum())].tolist()]
            scalars = prm(tokens[row : row + 1])[1][0]
            said, start = [" ".join(words[1 : P - 1])], P
            for j in range(P, len(words)):
                if words[j] in ("and", "<eos>"):
                    clause, start = " ".join(words[start:j]), j + 1
                    gold = rlhf.parse_review(clause + " <eos>") if clause not in said else None
                    said.append(clause)
                    right += (scalars[j].item() > 0) == ((gold if gold is not None else -6) > 0)
                    total += 1
    assert total > 10
    assert saved["held_out_clause_accuracy"] == pytest.approx(right / total)
    # the labels it cost: one a clause (a step closed by "and" or EOS) of the training pairs' responses
    train = torch.cat([chosen[:n_train], rejected[:n_train]]).tolist()
    closers = [rlhf.WORDS[t] in ("and", "<eos>") for row in train for t in tokens[row, P:][mask[row] > 0].tolist()]
    assert saved["clause_labels"] == sum(closers) and saved["train_pairs"] == n_train
    assert 0 <= saved["held_out_accuracy"] <= 1
    logged = tb_scalars(tmp_path / "process")["rlhf/rm_clause_accuracy"]
    # the results folder keeps both: the facts in the CSV's header, the accuracy per iteration in process/
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import results

    csv = results.write_run(tmp_path / "results", "reviews__arm__seed1", [], results.read_run(tmp_path / "process"))
    meta, _ = results.read_csv(csv)
    assert float(meta["rm_held_out_clause_accuracy"]) == pytest.approx(saved["held_out_clause_accuracy"], abs=1e-4)
    assert int(meta["rm_clause_labels"]) == sum(closers) and int(meta["rm_train_pairs"]) == n_train
    series = results.read_series(tmp_path / "results", "process")["arm", 1]
    np.testing.assert_allclose(series[:, 1], [value for _, value in logged], rtol=1e-5)


def test_the_process_rm_is_scaled_and_the_outcome_rm_shifted_too(tiny_run, tmp_path, monkeypatch):
    """Stage 2 normalizes the reward model's score through its head, on pi_SFT's responses: an outcome RM's to mean 0
    and std 1; a process RM's only scaled to std 1, each clause's score divided by the same number and nothing taken
    from it, since a shift would add the same to every clause and pay for writing more of them."""
    _, run_dir = tiny_run
    fitted = []
    fit = rlhf.fit

    def fit_seen(model, *rest):
        fit(model, *rest)
        fitted.append(copy.deepcopy(model))  # the reward model as fitted, before its normalization

    monkeypatch.setattr(rlhf, "fit", fit_seen)
    for reward, kind in (("outcome", rlhf.TinyLM), ("process", rlhf.ProcessRewardModel)):
        args = rlhf_tiny_args(tmp_path, reward, reward=reward, total_episodes=16)
        rlhf.train(rlhf.Args(**{**vars(args), "sft_checkpoint": str(run_dir / "sft.pt")}))
        saved = torch.load(tmp_path / reward / "reward_model.pt", weights_only=True)["model"]
        normalized = rlhf.new_model(args, "cpu", saved, kind=kind)
        sft = rlhf.new_model(args, "cpu", torch.load(run_dir / "sft.pt", weights_only=True)["model"])
        tokens, mask, *_ = rlhf.preference_pairs(sft, args, "cpu")
        with torch.no_grad():
            raw = fitted[-1].score(tokens, mask)
            scores = normalized.score(tokens, mask)
            assert raw.mean().abs() > 0.1 * raw.std()  # so that a shift would show
            if reward == "outcome":
                torch.testing.assert_close(scores, (raw - raw.mean()) / raw.std(), rtol=1e-4, atol=1e-5)
            else:  # each clause's score, at its closing token, is the fitted one divided by the std: no shift
                clauses = normalized.clause_scores(tokens, mask)
                torch.testing.assert_close(
                    clauses, fitted[-1].clause_scores(tokens, mask) / raw.std(), atol=1e-5, rtol=1e-4
                )
                assert scores.std().item() == pytest.approx(1.0, rel=1e-4) and scores.mean().abs() > 0.1


def refreshes_seen(monkeypatch):
    """Record each call of refresh_reward_model in a run: (the policy it sampled from, a copy of the policy's weights
    then, the tokens and mask it generated, every minibatch of pairs it trained on, the labels it returned), and the
    reward model's weights before and after."""
    seen = []
    refresh, generate, loss = rlhf.refresh_reward_model, rlhf.generate, rlhf.reward_model_loss

    def refresh_seen(reward_model, optimizer, policy, args):
        seen.append({"policy": policy, "weights": copy.deepcopy(policy.state_dict()), "pairs": []})
        seen[-1]["rm_before"] = copy.deepcopy(reward_model.state_dict())
        seen[-1]["labels"] = refresh(reward_model, optimizer, policy, args)
        seen[-1]["rm_after"] = copy.deepcopy(reward_model.state_dict())
        return seen[-1]["labels"]

    def generate_seen(lm, *rest):
        tokens, mask = generate(lm, *rest)
        if seen and "tokens" not in seen[-1]:
            seen[-1] |= {"lm": lm, "tokens": tokens, "mask": mask, "group_size": rest[-1]}
        return tokens, mask

    def loss_seen(reward_model, tokens, mask, chosen, rejected, labels):
        if seen and "rm_after" not in seen[-1]:
            seen[-1]["pairs"].append((tokens, chosen, rejected))
        return loss(reward_model, tokens, mask, chosen, rejected, labels)

    monkeypatch.setattr(rlhf, "refresh_reward_model", refresh_seen)
    monkeypatch.setattr(rlhf, "generate", generate_seen)
    monkeypatch.setattr(rlhf, "reward_model_loss", loss_seen)
    return seen


@pytest.mark.parametrize("reward", ["outcome", "process"])
def test_a_refresh_trains_the_rm_on_the_policys_current_samples_and_counts_their_labels(
    reward, tiny_run, tmp_path, monkeypatch
):
    """--rm-refresh 2 over 4 iterations: after iterations 2 and 4, the reward model trains on pairs of responses that
    the policy it is refreshed for samples then (two to a prompt, from weights that PPO has moved from pi_SFT's), each
    pair ranked by gold as stage 2's are, every pair once an epoch; and the run counts the labels: the pairs of
    different gold (an outcome RM), or the closing tokens of their responses (a process RM). The results folder keeps
    the count beside stage 2's."""
    _, run_dir = tiny_run
    seen = refreshes_seen(monkeypatch)
    args = rlhf_tiny_args(tmp_path, reward, reward=reward, rm_refresh=2, kl_coef=0.0, rm_epochs=2, rm_batch_size=4)
    agent, _ = rlhf.train(rlhf.Args(**{**vars(args), "sft_checkpoint": str(run_dir / "sft.pt")}))
    sft = torch.load(run_dir / "sft.pt", weights_only=True)["model"]
    assert len(seen) == 2
    counted = 0
    for refresh in seen:
        assert refresh["policy"] is agent.policy and refresh["lm"] is agent.policy and refresh["group_size"] == 2
        assert any(not torch.equal(w, sft[name]) for name, w in refresh["weights"].items())  # pi has moved from pi_SFT
        tokens, mask = refresh["tokens"], refresh["mask"]
        assert len(tokens) == 2 * args.batch_size and torch.equal(tokens[0::2, :6], tokens[1::2, :6])  # one prompt
        gold, _ = rlhf.gold_scores(tokens, mask)
        pairs = [
            (i, i + 1) if gold[i] > gold[i + 1] else (i + 1, i)
            for i in range(0, len(tokens), 2)
            if gold[i] != gold[i + 1]
        ]
        trained = [
            (c, r)
            for t, chosen, rejected in refresh["pairs"]
            for c, r in zip(chosen.tolist(), rejected.tolist(), strict=True)
        ]
        assert all(t is tokens for t, _, _ in refresh["pairs"])
        assert sorted(trained) == sorted(pairs * args.rm_epochs) and len(pairs) > 2  # each pair once an epoch
        assert any(not torch.equal(w, refresh["rm_after"][k]) for k, w in refresh["rm_before"].items())
        if reward == "outcome":
            labels = len(pairs)
        else:  # a label at each "and" or EOS of the pairs' responses
            rows = [row for pair in pairs for row in pair]
            words = [rlhf.WORDS[t] for row in rows for t in tokens[row, 6:][mask[row] > 0].tolist()]
            labels = sum(word in ("and", "<eos>") for word in words)
        assert refresh["labels"] == labels
        counted += labels
    checkpoint = torch.load(tmp_path / reward / "checkpoint.pt", weights_only=True)
    assert checkpoint["refresh_labels"] == counted and checkpoint["rm_optimizer"]["state"]
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import results

    csv = results.write_run(tmp_path / "results", "reviews__arm__seed1", [], results.read_run(tmp_path / reward))
    meta, _ = results.read_csv(csv)
    saved = torch.load(tmp_path / reward / "reward_model.pt", weights_only=True)
    assert int(meta["rm_refresh_labels"]) == counted and int(meta["rm_train_pairs"]) == saved["train_pairs"] > 0


def test_a_run_with_refreshes_stopped_and_resumed_ends_as_an_uninterrupted_one(tmp_path):
    """The refreshed reward model, its optimizer and the labels counted go into the checkpoint: a run stopped at its
    first checkpoint and resumed ends bit for bit where an uninterrupted one does."""
    flags = {"rm_refresh": 1, "kl_coef": 0.0, "save_every": 2}
    whole = whole_and_stopped(tmp_path, flags)
    assert torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)["iteration"] == 2
    resumed, _ = rlhf.train(rlhf_tiny_args(tmp_path, "cut", resume=str(tmp_path / "cut" / "checkpoint.pt"), **flags))
    for name, weight in whole.state_dict().items():
        assert torch.equal(weight, resumed.state_dict()[name]), name
    ends = [torch.load(tmp_path / run / "checkpoint.pt", weights_only=True) for run in ("whole", "cut")]
    assert ends[0]["refresh_labels"] == ends[1]["refresh_labels"] > 0
    for name, weight in ends[0]["reward_model"].items():
        assert torch.equal(weight, ends[1]["reward_model"][name]), name
