"""ppo_rlhf.py's train(), as tests/test_details.py checks the other scripts': one tiny run in this process, with what
stage 3 passes to its module-level math recorded, and each detail checked against what it implies, computed here
from the saved models: the score at the EOS (a fixed penalty without one), the KL penalty to the frozen pi_SFT, and
the mask that keeps the tokens after an EOS out of every loss."""

import pytest
import torch
from conftest import load_script, rlhf_tiny_args

rlhf = load_script("ppo_rlhf.py")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    # Responses of at most 8 tokens, so that some never reach their EOS; a beta that a dropped coefficient would show.
    path = tmp_path_factory.mktemp("rlhf")
    names = ["rollout", "compute_rewards", "compute_gae", "clipped_surrogate_loss", "value_loss"]
    args, calls = record_run(path, names, response_length=8, kl_coef=0.3, no_eos_score=-2.5)
    checkpoint = torch.load(path / "run" / "checkpoint.pt", weights_only=True)
    return args, calls, checkpoint


def record_run(path, names, **overrides):
    """A tiny run of train() in this process, with each call of the named functions recorded (args and result)."""
    args = rlhf_tiny_args(path, **overrides)
    calls = {name: [] for name in names}
    patch = pytest.MonkeyPatch()
    for name, log in calls.items():
        real = getattr(rlhf, name)

        def wrapper(*a, real=real, log=log, **kw):
            out = real(*a, **kw)
            log.append({"args": [x.detach().clone() if torch.is_tensor(x) else x for x in a], "kwargs": kw, "out": out})
            return out

        patch.setattr(rlhf, name, wrapper)
    try:
        rlhf.train(args)
    finally:
        patch.undo()
    return args, calls


def first_eos_mask(responses):
    """1 on each response up to and including its first EOS, on all of it if it has none: a plain loop."""
    mask = torch.zeros(responses.shape)
    for i, row in enumerate(responses.tolist()):
        for j, token in enumerate(row):
            mask[i, j] = 1.0
            if token == rlhf.EOS:
                break
    return mask


def test_the_mask_ends_at_the_first_eos(recorded):
    _, calls, _ = recorded
    for call in calls["rollout"]:
        batch = call["out"]
        assert torch.equal(batch["mask"], first_eos_mask(batch["responses"]))
    has_eos = torch.cat([(c["out"]["responses"] == rlhf.EOS).any(1) for c in calls["rollout"]])
    assert has_eos.any() and not has_eos.all(), "the run needs responses with and without an EOS"


def test_the_score_is_the_reward_models_at_the_eos_and_a_fixed_penalty_without_one(recorded):
    args, calls, checkpoint = recorded
    reward_model = rlhf.new_model(args, "cpu", checkpoint["reward_model"])
    for rollout, rewards in zip(calls["rollout"], calls["compute_rewards"], strict=True):
        batch = rollout["out"]
        scores = rewards["args"][0]
        has_eos = (batch["responses"] == rlhf.EOS).any(1)
        assert torch.all(scores[~has_eos] == args.no_eos_score)
        with torch.no_grad():
            at_eos = reward_model(batch["tokens"])[1]
        eos_position = rlhf.PROMPT_LENGTH + (batch["responses"] == rlhf.EOS).int().argmax(1)
        expected = at_eos[torch.arange(len(scores)), eos_position]
        torch.testing.assert_close(scores[has_eos], expected[has_eos])


def test_the_kl_penalty_is_to_the_frozen_sft_policy_with_beta(recorded):
    args, calls, checkpoint = recorded
    reference = rlhf.new_model(args, "cpu", checkpoint["reference"])
    for rollout, rewards in zip(calls["rollout"], calls["compute_rewards"], strict=True):
        batch = rollout["out"]
        _, logprobs, ref_logprobs, mask, kl_coef = rewards["args"]
        assert kl_coef == args.kl_coef
        assert torch.equal(mask, batch["mask"])
        with torch.no_grad():
            logits = reference(batch["tokens"])[0][:, rlhf.PROMPT_LENGTH - 1 : -1] / args.temperature
        expected = logits.log_softmax(-1).gather(-1, batch["responses"][..., None]).squeeze(-1)
        torch.testing.assert_close(ref_logprobs, expected)
    last = calls["compute_rewards"][-1]["args"]
    assert not torch.allclose(last[1], last[2]), "after some updates, pi_theta is not pi_SFT"


def test_gae_gets_these_rewards_and_the_mask(recorded):
    _, calls, _ = recorded
    for rewards, gae in zip(calls["compute_rewards"], calls["compute_gae"], strict=True):
        assert torch.equal(gae["args"][0], rewards["out"])
        assert torch.equal(gae["args"][2], rewards["args"][3])


def test_every_loss_reads_only_the_masked_tokens(recorded):
    _, calls, _ = recorded
    for name in ("clipped_surrogate_loss", "value_loss"):
        assert calls[name], name
        for call in calls[name]:
            mask = call["args"][-1] if len(call["args"]) in (4, 5) else call["kwargs"].get("mask")
            assert mask is not None and torch.is_tensor(mask), f"{name} was called without the mask"
            assert (mask == 0).any() and (mask == 1).any()
    for call in calls["clipped_surrogate_loss"]:
        advantages = call["args"][1]
        mask = call["args"][3]
        assert torch.all(advantages[mask == 0] == 0), "the advantages of tokens after an EOS are zero"


def baseline_by_loop(rewards, group_size, kind):
    """Each response's summed reward minus its group's mean (dr-grpo) or the mean of the others (rloo): plain loops."""
    totals = rewards.sum(1).tolist()
    advantages = []
    for start in range(0, len(totals), group_size):
        group = totals[start : start + group_size]
        for i, total in enumerate(group):
            others = group[:i] + group[i + 1 :]
            baseline = sum(others) / len(others) if kind == "rloo" else sum(group) / len(group)
            advantages.append(total - baseline)
    return torch.tensor(advantages)


@pytest.mark.parametrize("kind", ["dr-grpo", "rloo"])
def test_each_group_baseline_is_what_its_run_feeds_the_loss(kind, tmp_path):
    """A run with --advantage dr-grpo or rloo learns from its own advantage, not GRPO's."""
    args, calls = record_run(tmp_path, ["rollout", "compute_rewards", "clipped_surrogate_loss"], advantage=kind)
    fed = torch.cat([call["args"][1].flatten() for call in calls["clipped_surrogate_loss"]])
    for rollout, rewards in zip(calls["rollout"], calls["compute_rewards"], strict=True):
        batch, mask = rollout["out"], rewards["args"][3]
        expected = baseline_by_loop(rewards["out"], args.group_size, kind)[:, None] * mask
        torch.testing.assert_close(batch["advantages"], expected)  # what the update's minibatches are cut from
        grpo = rlhf.grpo_advantages(rewards["out"].sum(1).view(-1, args.group_size)).view(-1, 1) * mask
        assert not torch.allclose(batch["advantages"], grpo), "the check would not see GRPO's advantage"
    # and the loss got those advantages: every value it saw is one of the batches' (the minibatches are their rows)
    batches = torch.cat([rollout["out"]["advantages"].flatten() for rollout in calls["rollout"]])
    assert torch.isin(fed, batches).all()


def test_the_adaptive_kl_run_feeds_its_rewards_the_controllers_beta(tmp_path):
    """With --adaptive-kl, each iteration's rewards use the beta that Ziegler et al.'s controller
    made from the previous iteration's KL to pi_SFT, starting from --kl-coef."""
    args, calls = record_run(tmp_path, ["compute_rewards"], adaptive_kl=True, kl_coef=0.05, kl_target=0.5)
    betas = [call["args"][4] for call in calls["compute_rewards"]]
    assert betas[0] == args.kl_coef
    for i, call in enumerate(calls["compute_rewards"][:-1]):
        _, logprobs, ref_logprobs, mask, beta = call["args"]
        kl = ((logprobs - ref_logprobs) * mask).sum(1).mean().item()  # the KL per response, in nats
        error = min(max(kl / args.kl_target - 1.0, -0.2), 0.2)
        assert betas[i + 1] == pytest.approx(beta * (1 + error * args.batch_size / args.kl_horizon), rel=1e-5)
    assert len(set(betas)) == len(betas), "beta moves every iteration"


def test_an_ipo_run_trains_on_ipos_loss_and_not_dpos(tmp_path):
    """With --dpo --ipo, stage 3's minibatches reach IPO's loss; DPO's log-sigmoid (the reward model's
    Bradley-Terry loss) is then called by stage 2 alone. Stages 1 and 2 come from one checkpoint, for both runs."""
    _, dpo = record_run(tmp_path, ["preference_loss", "dpo_update"], dpo=True, kl_coef=0.1)
    stages = {"sft_checkpoint": str(tmp_path / "run" / "sft.pt")}
    stages |= {"reward_model_checkpoint": str(tmp_path / "run" / "reward_model.pt")}
    args, ipo = record_run(
        tmp_path / "ipo", ["preference_loss", "dpo_update"], dpo=True, ipo=True, kl_coef=0.1, **stages
    )
    updates = len(ipo["dpo_update"])
    assert (
        updates == args.total_episodes // args.batch_size * args.update_epochs * args.batch_size // args.minibatch_size
    )
    assert len(dpo["preference_loss"]) > updates and len(ipo["preference_loss"]) == 0
    losses = [call["out"]["loss"].item() for call in ipo["dpo_update"]]
    assert all(loss >= 0 for loss in losses) and losses != [c["out"]["loss"].item() for c in dpo["dpo_update"]]
