# /// script
# requires-python = ">=3.11"
# dependencies = ["torch==2.13.0", "tyro==1.0.17", "tensorboard==2.21.0", "wandb==0.31.0"]
# ///
"""PPO as RLHF uses it, in one file: the three stages of Ziegler et al. 2019 (arXiv:1909.08593) on a tiny transformer
trained from scratch on a synthetic language of film reviews. Stage 1 fits pi_SFT to the language, stage 2 a reward
model to pairs of pi_SFT's samples ranked by a hidden gold reward, and stage 3 fine-tunes pi_SFT on the RM's score
with PPO-Clip (Schulman et al. 2017, arXiv:1707.06347, eq. (7), (9), (11)-(12)) and a KL penalty to pi_SFT (Ziegler
et al. §2). The gold reward shows what the reward model cannot: whether a rising score is real.

    python ppo_rlhf.py                     # the three stages, on a CPU, in minutes: RM and gold scores rise
    python ppo_rlhf.py --kl-coef 0         # no leash: the RM's score holds or rises as the gold score peaks and falls
    python ppo_rlhf.py --advantage grpo    # GRPO's group-relative advantage in place of the critic and GAE
"""

import contextlib
import copy
import itertools
import math
import os
import random
import re
import signal
import sys
import time
from dataclasses import asdict, dataclass
from typing import Literal

import torch
import torch.nn as nn
import torch.nn.functional as F

SCRIPT = "ppo_rlhf.py"  # what a checkpoint names, not __file__'s: a renamed copy resumes its own, and this file's


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]  # this file's name: part of the run directory's name
    seed: int = 1  # seed of the grammar's samples and of torch: on the CPU, one seed gives one run
    device: str = "auto"  # torch device: auto, cpu, cuda, cuda:1, ... (auto: cuda when there is one)
    compile: bool = False  # apply torch.compile to the agent's forward, which rollouts and PPO's updates run
    torch_threads: int = 1  # torch CPU threads
    run_dir: str | None = None  # where logs and checkpoints go (None: runs/reviews__{exp_name}__{seed}__{time})
    track: bool = False  # mirror the TensorBoard scalars to Weights & Biases, as CleanRL's --track
    wandb_project_name: str = "ppo"  # the W&B project of a --track run
    wandb_entity: str | None = None  # the W&B team or user of a --track run (None: your default entity)
    # The networks: one causal transformer shape for pi_SFT, the reward model, the policy and the critic
    d_model: int = 64  # width of the transformer
    n_layer: int = 2  # number of transformer blocks
    n_head: int = 4  # attention heads per block; must divide --d-model
    response_length: int = 24  # the most tokens a response may have, its EOS included
    temperature: float = 1.0  # sampling temperature, also used to recompute every log-prob
    # Stage 1: the supervised model pi_SFT, fitted to reviews sampled from the grammar
    sft_steps: int = 600  # gradient steps of next-token prediction
    sft_batch_size: int = 64  # reviews per step
    sft_learning_rate: float = 1e-3  # Adam step size
    # Stage 2: the reward model, fitted to pairs of pi_SFT's responses ranked by the gold reward
    rm_pairs: int = 4096  # comparisons sampled (ties dropped), a tenth held out: fewer make a worse proxy (Gao et al.)
    rm_epochs: int = 4  # epochs over the training pairs
    rm_batch_size: int = 64  # pairs per step
    rm_learning_rate: float = 1e-3  # Adam step size
    rm_ensemble: int = 1  # K reward models, on the same pairs, each with its own seed's order and head (Coste et al.)
    rm_same_head: bool = False  # an ablation: the K members all start from the zero head and differ in order only
    rm_ensemble_agg: Literal["mean", "min", "uwo"] = "mean"  # how stage 3 scores with K: uwo is mean - lambda variance
    uwo_coef: float = 0.1  # lambda of uwo, the weight of the members' variance (Coste et al.'s PPO setting)
    reward: Literal["outcome", "process"] = "outcome"  # one score a response, or one a clause (ProcessRewardModel)
    rm_refresh: int = 0  # every K iterations, the RM learns on gold's labels of pi's current responses (0: never)
    # Stage 3: PPO against the reward model
    total_episodes: int = 12_800  # responses sampled in all, rounded down to whole batches
    batch_size: int = 64  # prompts per rollout
    minibatch_size: int = 32  # responses per minibatch; must divide --batch-size
    update_epochs: int = 4  # epochs K over each rollout
    learning_rate: float = 1e-4  # Adam step size of the policy and its critic, constant (Ziegler et al. anneal it to 0)
    kl_coef: float = 0.05  # beta of the per-token penalty -beta (log pi - log pi_SFT), TRL's default; 0: no leash
    adaptive_kl: bool = False  # adapt beta toward --kl-target with Ziegler et al.'s controller
    kl_target: float = 2.0  # the KL[pi || pi_SFT] per response, in nats, that the controller aims at
    kl_horizon: int = 1000  # the controller's horizon, in responses (Ziegler et al.'s code: 10000, for longer runs)
    gamma: float = 1.0  # discount over tokens
    gae_lambda: float = 0.95  # GAE lambda over tokens
    clip_coef: float = 0.2  # clip range epsilon of L^CLIP, also the value loss's
    vf_coef: float = 0.1  # c1 of eq. (9); Adam undoes it on the default critic's own weights, but for the shared clip
    max_grad_norm: float = 1.0  # clip the global gradient norm to this
    no_eos_score: float = -3.0  # the score of a response that never ends (no EOS), in the RM's normalized units
    value_model: Literal["reward-model", "policy-head"] = "reward-model"  # a critic started from the RM, or a head
    advantage: Literal["gae", "grpo", "dr-grpo", "rloo"] = "gae"  # gae: the critic and GAE; else a group baseline
    group_size: int = 8  # grpo, dr-grpo, rloo: responses sampled for each prompt, one group; divides --batch-size
    dpo: bool = False  # stage 3 is DPO on the reward model's own training pairs, with beta --kl-coef, in place of PPO
    ipo: bool = False  # with --dpo, IPO's loss (Azar et al. 2023): the margin's squared distance from 1 / (2 beta)
    kto: bool = False  # stage 3 is KTO (Ethayarajh et al. 2024) on the RM's pairs taken apart, with beta --kl-coef
    kto_weights: tuple[float, float] = (1.0, 1.0)  # KTO's lambda_D and lambda_U, of desirable and undesirable responses
    kto_desirable_share: float = 1.0  # the share of the desirable (chosen) responses KTO keeps: its imbalanced data
    sft_checkpoint: str | None = None  # skip stage 1: take pi_SFT from this sft.pt
    reward_model_checkpoint: str | None = None  # skip stage 2: take the reward model from this reward_model.pt
    save_every: int = 25  # save the PPO checkpoint, and print samples, every this many iterations (and at the end)
    resume: str | None = None  # continue the PPO stage saved in this checkpoint, with its hyperparameters


# THE MATH
def masked_mean(x, mask=None):
    return x.mean() if mask is None else (x * mask).sum() / mask.sum()


def compute_rewards(scores, logprobs, ref_logprobs, mask, kl_coef):
    """Ziegler et al.'s R(x, y) = r(x, y) - beta log(pi(y|x) / pi_SFT(y|x)) over the tokens [B, L]: -beta times each
    token's log-ratio, and the score at the last masked position (a row with no EOS gets its penalty as its score);
    or, with --reward process, scores [B, L]: a score at each clause's closing token, where they stand.

    Its expectation over pi's responses is the objective E[r] - beta KL[pi || pi_SFT], whose maximum is pi* = pi_SFT
    exp(r / beta) / Z. So beta sets how far pi may move from pi_SFT; at beta = 0 the optimum is the argmax of r, one
    response (the entropy collapses onto whatever the RM overrates); the log-ratio (k1) sits in the reward because
    its mean over pi's own samples is that KL; and DPO (Rafailov et al. 2023) solves for pi* from pairs directly."""
    rewards = kl_coef * (ref_logprobs - logprobs) * mask
    if scores.dim() == 2:  # process supervision: the clauses' scores stay at their own tokens
        return rewards + scores * mask
    rewards[torch.arange(len(scores)), mask.sum(1).long() - 1] += scores
    return rewards


def compute_gae(rewards, values, mask, gamma, gae_lambda):
    """Generalized advantage estimation, paper eq. (11)-(12), over the tokens of [B, L] responses. A response ends at
    its last masked position: the values after it count as 0. The returns A + V are the value function's targets.

    >>> compute_gae(torch.tensor([[0.0, 1.0, 0.0]]), torch.zeros(1, 3), torch.tensor([[1.0, 1.0, 0.0]]), 1, 0.5)[0]
    tensor([[0.5000, 1.0000, 0.0000]])
    """
    values = values * mask
    next_values = torch.cat([values[:, 1:], torch.zeros_like(values[:, :1])], 1)
    # The paper's eq. (12), for all t at once: delta_t = r_t + gamma V(s_{t+1}) - V(s_t).
    deltas = rewards * mask + gamma * next_values - values
    # Then eq. (11), backwards over the tokens: A_t = delta_t + gamma lambda A_{t+1}, 0 after the end (delta is 0).
    advantages = torch.zeros_like(rewards)
    lastgaelam = torch.zeros_like(rewards[:, 0])
    for t in reversed(range(rewards.shape[1])):
        lastgaelam = deltas[:, t] + gamma * gae_lambda * lastgaelam
        advantages[:, t] = lastgaelam
    return advantages, advantages + values


def clipped_surrogate_loss(ratio, advantages, clip_coef, mask=None):
    """Minus L^CLIP, paper eq. (7): -E[min(r A, clip(r, 1 - eps, 1 + eps) A)], here over the masked tokens."""
    surr1 = ratio * advantages
    surr2 = torch.clamp(ratio, 1.0 - clip_coef, 1.0 + clip_coef) * advantages
    return -masked_mean(torch.min(surr1, surr2), mask)


def value_loss(newvalue, oldvalue, returns, clip_coef, mask):
    """L^VF of paper eq. (9), the squared error (V - V_targ)^2 over the masked tokens, clipped (core detail 9, not the
    paper's): the larger of the errors of V and of the old value moved at most clip_coef to V."""
    v_loss_unclipped = (newvalue - returns) ** 2
    v_clipped = oldvalue + torch.clamp(newvalue - oldvalue, -clip_coef, clip_coef)
    return masked_mean(torch.max(v_loss_unclipped, (v_clipped - returns) ** 2), mask)


def preference_loss(chosen_scores, rejected_scores):
    """The Bradley-Terry loss of a reward model, -log sigmoid(r_w - r_l), averaged over pairs."""
    return -F.logsigmoid(chosen_scores - rejected_scores).mean()


def pairwise_accuracy(scores, gold, prompts):
    """How good a proxy the RM is here, on the kind of pair it learned from: two responses to one prompt, of different
    gold. Returns the share of such pairs it ranks as gold does (nan if none), and their number."""
    differ = (gold[:, None] > gold[None, :]) & (prompts[:, None] == prompts[None, :])
    return ((scores[:, None] > scores[None, :]) & differ).sum() / differ.sum(), differ.sum()


def adapt_kl_coef(kl_coef, kl, target, n_steps, horizon):
    """Ziegler et al.'s controller (§2.2): beta <- beta (1 + K e), e = clip(KL / target - 1, -0.2, 0.2), K = n_steps /
    horizon for the n_steps responses of the update. Not the PPO paper's §4 rule, which doubles or halves beta when
    the KL between successive policies leaves [d_targ / 1.5, 1.5 d_targ], to keep each update small: here the KL is
    to the fixed pi_SFT, and beta moves by at most 0.2 K, to keep the run near pi_SFT (PPO-Clip bounds each update).

    >>> adapt_kl_coef(1.0, 12.0, 6.0, 500, 1000), adapt_kl_coef(1.0, 0.0, 6.0, 500, 1000)  # e clipped to +-0.2
    (1.1, 0.9)
    """
    proportional_error = min(max(kl / target - 1.0, -0.2), 0.2)
    return kl_coef * (1.0 + proportional_error * n_steps / horizon)


# ENVIRONMENT: a language of film reviews, its hidden gold reward, prompts, and sampling
NOUNS = ["film", "plot", "cast", "music", "ending", "script", "pace", "set"]
VALENCE = {"awful": -3, "bad": -2, "dull": -1, "fine": 1, "good": 2, "superb": 3}
MODIFIERS = {"very": 2, "not": -1}
# PAD, BOS and EOS are distinct: PAD fills the tail of a sequence, and no loss or statistic reads it.
WORDS = ["<pad>", "<bos>", "<eos>", "the", "was", "and", *MODIFIERS, *NOUNS, *VALENCE]
PAD, BOS, EOS = range(3)
TOKEN = {word: i for i, word in enumerate(WORDS)}
PROMPT_LENGTH = 6  # "<bos> the NOUN was ADJ and": a review's first clause, which a response goes on from
BLOCK_SIZE = 32  # the longest sequence, prompt and response, that the networks take
POOL = 640  # the most recent responses (ten rollouts of 64) on which the RM's accuracy is measured
GOLD_PENALTY = -6.0  # the gold score of text a reader rejects, garbled or spam: that of one "very awful" clause
CLAUSE = rf"the ({'|'.join(NOUNS)}) was (?:(very|not) )?({'|'.join(VALENCE)})"


def sample_review(rng):
    """Words of a review from the grammar: 1 to 3 clauses "the NOUN was [very|not] ADJ" joined by "and", then EOS, and
    as people write, no clause twice. A policy may write more clauses, or repeat one: the gold reward judges both, and
    the reward model has seen neither."""
    clauses = []
    while len(clauses) < 3:
        modifier = rng.choice(["", "", "very", "not"])
        words = ["the", rng.choice(NOUNS), "was", modifier, rng.choice(list(VALENCE))]
        clause = " ".join(word for word in words if word)
        if clause not in clauses:
            clauses.append(clause)
            if rng.random() < 0.5:
                break
    return " and ".join(clauses).split() + ["<eos>"]


def review_form(text):
    """How a reader takes a text: "garbled" outside the grammar, "spam" if it says a clause twice word for word, else
    "well formed". The reward model never saw spam (pi_SFT's samples never repeat a clause) and hardly any garbled
    text: blind spots in its data, where a policy without a leash may find the scores that gold denies."""
    if not re.fullmatch(rf"{CLAUSE}( and {CLAUSE})* <eos>", text):
        return "garbled"
    clauses = re.findall(CLAUSE, text)
    return "spam" if len(set(clauses)) < len(clauses) else "well formed"


def parse_review(text):
    """The gold value of a review as a reader judges it, or None if it is not well formed: the sum of its clauses'
    valences (x2 after "very", x-1 after "not"), unless it says a clause twice word for word. A reader takes praise
    that repeats itself for spam, and scores it as garbled text.

    >>> parse_review("the film was very good and the plot was not bad <eos>"), parse_review("the film was <eos>")
    (6, None)
    >>> parse_review("the film was good and the film was good <eos>")
    -6.0
    """
    form = review_form(text)
    if form != "well formed":
        return None if form == "garbled" else GOLD_PENALTY
    return sum(MODIFIERS.get(modifier, 1) * VALENCE[adjective] for _, modifier, adjective in re.findall(CLAUSE, text))


def gold_scores(tokens, mask):
    """The hidden gold reward of each sequence [B, T], what the RM should learn, and the share of each form of text
    {well_formed, spam, garbled}, each a [B] tensor of 0s and 1s: the hacks by name."""
    lengths = (PROMPT_LENGTH + mask.sum(1).long()).tolist()
    texts = [" ".join(WORDS[t] for t in row[1:n]) for row, n in zip(tokens.tolist(), lengths, strict=True)]
    gold = torch.tensor([GOLD_PENALTY if (value := parse_review(text)) is None else float(value) for text in texts])
    forms = [review_form(text) for text in texts]
    shares = {name: [form == name.replace("_", " ") for form in forms] for name in ("well_formed", "spam", "garbled")}
    return gold.to(tokens.device), {name: torch.tensor(x).float().to(tokens.device) for name, x in shares.items()}


@torch.no_grad()
def clause_golds(tokens, mask):
    """Process supervision's labels [B, L]: each step's gold value at the token that closes it ("and" or EOS), 0
    elsewhere; and where those tokens are. A clause has its valence (x2 after "very", x-1 after "not"); a step that is
    no clause (garbled), or says one already said, the prompt's included (spam), GOLD_PENALTY."""
    labels = torch.zeros_like(mask)
    for i, row in enumerate(tokens.tolist()):
        words = [WORDS[t] for t in row[: PROMPT_LENGTH + int(mask[i].sum())]]
        said = [" ".join(words[1 : PROMPT_LENGTH - 1])]  # the prompt's clause
        start = PROMPT_LENGTH
        for j in [j for j in range(PROMPT_LENGTH, len(words)) if words[j] in ("and", "<eos>")]:
            clause = " ".join(words[start:j])
            match = re.fullmatch(CLAUSE, clause) if clause not in said else None
            labels[i, j - PROMPT_LENGTH] = MODIFIERS.get(match[2], 1) * VALENCE[match[3]] if match else GOLD_PENALTY
            said.append(clause)
            start = j + 1
    return labels, (labels != 0).float()  # no step's gold is 0: the labels stand where the steps close


def generate(lm, n, response_length, temperature, group_size=1):
    """n prompts "<bos> the NOUN was ADJ and", each group_size times, and lm's responses: sequences [n group_size,
    P + L] with PAD after the first EOS, and their mask, 1 on a response up to its first EOS included (on all of it if
    it has none). Gold counts the prompt's clause: a response's baseline should know its prompt (a critic, a group)."""
    prompts = torch.tensor([[BOS, TOKEN["the"], 0, TOKEN["was"], 0, TOKEN["and"]]] * n, device=lm.lm_head.weight.device)
    prompts[:, 2] = torch.randint(len(NOUNS), (n,)) + TOKEN[NOUNS[0]]  # the NOUN
    prompts[:, 4] = torch.randint(len(VALENCE), (n,)) + TOKEN["awful"]  # was ADJ
    tokens = prompts.repeat_interleave(group_size, 0)
    for _ in range(response_length):
        logits = lm(tokens)[0][:, -1] / temperature
        tokens = torch.cat([tokens, torch.multinomial(logits.softmax(-1), 1)], 1)
        if (tokens[:, PROMPT_LENGTH:] == EOS).any(1).all():
            break
    responses = F.pad(tokens[:, PROMPT_LENGTH:], (0, PROMPT_LENGTH + response_length - tokens.shape[1]), value=PAD)
    is_eos = (responses == EOS).long()
    mask = ((is_eos.cumsum(1) - is_eos) == 0).float()
    return torch.cat([tokens[:, :PROMPT_LENGTH], responses.masked_fill(mask == 0, PAD)], 1), mask


# AGENT: a tiny causal transformer, the policy, and its value function
class TinyLM(nn.Module):
    """A causal transformer in GPT-2's layout (pre-LayerNorm blocks of self-attention and a 4x wider MLP) with two
    heads: next-token logits, and a scalar at each position, the reward model's score (read at the EOS) or a value."""

    def __init__(self, d_model, n_layer, n_head):
        super().__init__()
        self.tok_emb = nn.Embedding(len(WORDS), d_model)
        self.pos_emb = nn.Embedding(BLOCK_SIZE, d_model)
        block = nn.TransformerEncoderLayer(d_model, n_head, 4 * d_model, 0.0, "gelu", batch_first=True, norm_first=True)
        self.blocks = nn.TransformerEncoder(block, n_layer, enable_nested_tensor=False)
        self.ln_f = nn.LayerNorm(d_model)
        self.lm_head = nn.Linear(d_model, len(WORDS), bias=False)
        self.score_head = nn.Linear(d_model, 1)
        nn.init.zeros_(self.score_head.weight)  # the scalar starts at 0
        nn.init.zeros_(self.score_head.bias)

    def forward(self, tokens):
        # Causal: a position sees only those before it, so the PADs after an EOS change nothing before them.
        x = self.tok_emb(tokens) + self.pos_emb(torch.arange(tokens.shape[1], device=tokens.device))
        causal = nn.Transformer.generate_square_subsequent_mask(tokens.shape[1], device=tokens.device)
        x = self.ln_f(self.blocks(x, mask=causal, is_causal=True))
        return self.lm_head(x), self.score_head(x).squeeze(-1)

    def score(self, tokens, mask):
        """The scalar of each sequence at its last response token (the EOS, if it has one): a reward model's score."""
        return self(tokens)[1][torch.arange(len(tokens)), PROMPT_LENGTH + mask.sum(1).long() - 1]


class ProcessRewardModel(TinyLM):
    """--reward process, process supervision (Uesato et al. 2022, Lightman et al. 2023): a reward model read at each
    clause's closing token, fitted to each clause's gold value (clause_golds). It can say which clause is bad, where the
    outcome RM gives a response one number and must learn which part earned it; it cannot know what it never saw
    either: in pi_SFT's samples no clause is said twice."""

    def clause_scores(self, tokens, mask):
        """The scalar at each response token that closes a clause ("and" or EOS), 0 elsewhere [B, L]."""
        closes = (tokens[:, PROMPT_LENGTH:] == TOKEN["and"]) | (tokens[:, PROMPT_LENGTH:] == EOS)
        return self(tokens)[1][:, PROMPT_LENGTH:] * closes * mask

    def score(self, tokens, mask):
        """A response's whole score: the sum of its clauses'."""
        return self.clause_scores(tokens, mask).sum(1)


class Agent(nn.Module):
    """The policy pi_theta, started from pi_SFT, and its value function: by default a critic started from the RM,
    which reads responses as the RM does and cannot pull on the policy's weights; or a head on the policy (faster)."""

    def __init__(self, sft, reward_model, value_model):
        super().__init__()
        self.policy = copy.deepcopy(sft)
        first = reward_model[0] if isinstance(reward_model, Ensemble) else reward_model  # an ensemble's first member
        self.critic = copy.deepcopy(first) if value_model == "reward-model" else None

    def forward(self, tokens):
        """Logits and values at every position; position t holds what predicts token t + 1."""
        logits, values = self.policy(tokens)
        return logits, values if self.critic is None else self.critic(tokens)[1]


def new_model(args, device, state=None, members=1, kind=TinyLM):
    model = kind(args.d_model, args.n_layer, args.n_head)
    model = (model if members == 1 else Ensemble([copy.deepcopy(model) for _ in range(members)], args)).to(device)
    if state is not None:
        model.load_state_dict(state)
    return model


def response_dist(logits, temperature):
    """The distribution of each response token [B, L] from logits [B, P + L, V], at the sampling temperature."""
    return torch.distributions.Categorical(logits=logits[:, PROMPT_LENGTH - 1 : -1] / temperature, validate_args=False)


# TRAINING
def fit(model, loss_fn, steps, learning_rate, stage, stop, saved):
    """Stages 1 and 2: `steps` Adam steps on loss_fn(step), with the loss in the progress lines. `saved`: what a stop
    leaves on disk, and how to go on from it."""
    optimizer = torch.optim.Adam(model.parameters(), lr=learning_rate)
    start = time.time()
    for step in range(1, steps + 1):
        loss = loss_fn(step)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        if not math.isfinite(loss.item()):
            raise Diverged(f"the loss of stage {stage} is not finite at step {step}; try a smaller learning rate")
        report(f"stage {stage}: step", step, steps, start, f"loss {loss.item():.3f}")
        if stop:
            raise Stopped(f"stopped in stage {stage} at step {step}; {saved}")


def train_sft(args, run_dir, device, stop):
    """Stage 1: pi_SFT, a transformer fitted to reviews from the grammar by next-token prediction."""
    if args.sft_checkpoint:
        return new_model(args, device, load_checkpoint(args.sft_checkpoint, args, "sft")[0]["model"])
    torch.manual_seed(args.seed)
    rng = random.Random(args.seed)
    sft = new_model(args, device)

    def loss_fn(step):
        rows = [[BOS] + [TOKEN[w] for w in sample_review(rng)] for _ in range(args.sft_batch_size)]
        tokens = torch.tensor([row + [PAD] * (BLOCK_SIZE - len(row)) for row in rows], device=device)
        # The EOS is a target like any word; the PADs after it are none.
        return F.cross_entropy(sft(tokens[:, :-1])[0].transpose(1, 2), tokens[:, 1:], ignore_index=PAD)

    fit(sft, loss_fn, args.sft_steps, args.sft_learning_rate, "1, SFT", stop, "nothing is saved yet: start again")
    save_checkpoint(os.path.join(run_dir, "sft.pt"), "sft", args, model=sft.state_dict())
    return sft


def preference_pairs(sft, args, device):
    """Pairs of pi_SFT's responses to one prompt ranked by the gold reward, ties dropped: (tokens, mask, chosen,
    rejected, n_train), the first n_train pairs to learn from and a tenth held out. The same for the RM and for DPO."""
    torch.manual_seed(args.seed + 1)
    n = args.rm_pairs  # sampled 256 prompts (512 responses) at a time: larger batches run slower on a CPU
    samples = [generate(sft, min(256, n - i), args.response_length, args.temperature, 2) for i in range(0, n, 256)]
    tokens, mask = map(torch.cat, zip(*samples, strict=True))
    chosen, rejected = ranked_pairs(tokens, mask)
    n_train = len(chosen) - len(chosen) // 10
    if n_train == len(chosen):
        raise Diverged(f"only {len(chosen)} pairs differ in gold reward: raise --sft-steps or --rm-pairs")
    return tokens, mask, chosen, rejected, n_train


def ranked_pairs(tokens, mask):
    """Rows 2i and 2i + 1 of `tokens`, two responses to a prompt, as (chosen, rejected) by gold, ties dropped."""
    gold, _ = gold_scores(tokens, mask)
    a = torch.arange(0, len(tokens), 2, device=tokens.device)[gold[0::2] != gold[1::2]]
    return a + (gold[a + 1] > gold[a]), a + (gold[a] > gold[a + 1])


def reward_model_loss(reward_model, tokens, mask, chosen, rejected, labels):
    """The loss on pairs of rows: Bradley-Terry's of the scores, or a process RM's squared errors from clause golds."""
    if isinstance(reward_model, ProcessRewardModel):
        rows = torch.cat([chosen, rejected])
        error = reward_model.clause_scores(tokens[rows], mask[rows]) - labels[rows]
        return (error**2).sum() / (labels[rows] != 0).sum()
    r_w = reward_model.score(tokens[chosen], mask[chosen])
    return preference_loss(r_w, reward_model.score(tokens[rejected], mask[rejected]))


def train_reward_model(args, sft, run_dir, device, stop):
    """Stage 2: a reward model, pi_SFT with its scalar head read at the EOS, fitted to pairs of pi_SFT's responses
    ranked by the gold reward; or a process RM, fitted to each clause's gold on the same responses. It only ever sees
    pi_SFT's text: what it says of any other text is a guess."""
    kind = ProcessRewardModel if args.reward == "process" else TinyLM
    if args.reward_model_checkpoint:
        state = load_checkpoint(args.reward_model_checkpoint, args, "reward_model")[0]["model"]
        return new_model(args, device, state, args.rm_ensemble, kind)
    tokens, mask, chosen, rejected, n_train = preference_pairs(sft, args, device)
    labels, ends = clause_golds(tokens, mask)
    steps = math.ceil(n_train * args.rm_epochs / args.rm_batch_size)
    saved = f"stage 1 is saved: go on with --sft-checkpoint {args.sft_checkpoint or os.path.join(run_dir, 'sft.pt')}"
    members = []
    for k in range(args.rm_ensemble):
        if k:  # member k > 0: the same pairs, in the order of a seed of its own
            torch.manual_seed(args.seed + 1 + 1000 * k)
        order = torch.cat([torch.randperm(n_train, device=device) for _ in range(args.rm_epochs)])
        reward_model = copy.deepcopy(sft) if kind is TinyLM else new_model(args, device, sft.state_dict(), kind=kind)
        if args.rm_ensemble > 1 and not args.rm_same_head:  # and a score head drawn from that seed, as Coste et al.'s
            reward_model.score_head.reset_parameters()

        def loss_fn(step, order=order, reward_model=reward_model):
            mb_inds = order[(step - 1) * args.rm_batch_size : step * args.rm_batch_size]
            return reward_model_loss(reward_model, tokens, mask, chosen[mb_inds], rejected[mb_inds], labels)

        fit(reward_model, loss_fn, steps, args.rm_learning_rate, "2, reward model", stop, saved)
        # Normalize the score, through the scalar head, to std 1 on pi_SFT's responses and to mean 0; but a process RM
        # is not shifted: a shift would add the same to every clause, and pay for writing more of them.
        with torch.no_grad():
            scores = reward_model.score(tokens, mask)
            reward_model.score_head.weight.div_(scores.std())
            reward_model.score_head.bias.sub_(0 if kind is ProcessRewardModel else scores.mean()).div_(scores.std())
        members.append(reward_model)
    reward_model = members[0] if args.rm_ensemble == 1 else Ensemble(members, args)
    with torch.no_grad():
        scores = reward_model.score(tokens, mask)
    accuracy = (scores[chosen[n_train:]] > scores[rejected[n_train:]]).float().mean().item()
    print(f"stage 2: the reward model ranks {accuracy:.1%} of {len(chosen) - n_train} held-out pairs as gold does")
    state = {"model": reward_model.state_dict(), "held_out_accuracy": accuracy, "train_pairs": n_train}
    if kind is ProcessRewardModel:  # and how often it rates a held-out clause good or bad as gold does
        held_out = torch.cat([chosen[n_train:], rejected[n_train:]])
        scores = reward_model.clause_scores(tokens[held_out], mask[held_out])
        right, closes = clause_right(scores, tokens[held_out], mask[held_out])
        state["held_out_clause_accuracy"] = (right.sum() / closes.sum()).item()
        train = torch.cat([chosen[:n_train], rejected[:n_train]])  # the labels it cost, beside the pairs compared
        state["clause_labels"] = int(ends[train].sum())
        print(f"stage 2: it rates {state['held_out_clause_accuracy']:.1%} of held-out clauses good or bad as gold does")
    save_checkpoint(os.path.join(run_dir, "reward_model.pt"), "reward_model", args, **state)
    return reward_model


def refresh_reward_model(reward_model, optimizer, policy, args):
    """--rm-refresh: the reward model (not frozen) keeps learning on pi's text, as Bai et al. 2022's iterated online
    RLHF and Llama 2's do, where stage 2 showed it pi_SFT's alone: pairs of pi's current responses to --batch-size
    prompts, labelled as stage 2's were, and --rm-epochs epochs of clipped steps (gradient_step) of its own Adam, kept
    across refreshes. Its head keeps stage 2's normalization. Returns the labels used: the pairs, or their clauses."""
    tokens, mask = generate(policy, args.batch_size, args.response_length, args.temperature, 2)
    chosen, rejected = ranked_pairs(tokens, mask)
    labels, ends = clause_golds(tokens, mask)
    for _ in range(args.rm_epochs):
        for mb_inds in torch.randperm(len(chosen), device=tokens.device).split(args.rm_batch_size):
            loss = reward_model_loss(reward_model, tokens, mask, chosen[mb_inds], rejected[mb_inds], labels)
            gradient_step(reward_model, optimizer, loss, args)
    process = isinstance(reward_model, ProcessRewardModel)
    return int(ends[torch.cat([chosen, rejected])].sum()) if process else len(chosen)


def clause_right(clause_scores, tokens, mask):
    """Where a process RM's clause_scores rate a clause good or bad (by their sign) as gold does: 1 at those closing
    tokens [B, L]; and the closing tokens."""
    labels, ends = clause_golds(tokens, mask)
    return (clause_scores.sign() == labels.sign()) * ends, ends


@torch.no_grad()
def rollout(agent, reference, reward_model, args):
    """Responses to prompts from pi_theta_old (--group-size a prompt with GRPO), and what PPO needs, [B, ...] each."""
    group_size = 1 if args.advantage == "gae" else args.group_size
    n = args.batch_size // group_size
    tokens, mask = generate(agent.policy, n, args.response_length, args.temperature, group_size)
    responses = tokens[:, PROMPT_LENGTH:]
    logits, values = agent(tokens)
    # The log-probs are recomputed as the tokens were sampled, at the same temperature: the ratio starts at 1.
    dist = response_dist(logits, args.temperature)
    ref_logprobs = response_dist(reference(tokens)[0], args.temperature).log_prob(responses)
    has_eos = (responses == EOS).any(1)
    batch = {"tokens": tokens, "responses": responses, "mask": mask, "logprobs": dist.log_prob(responses)}
    if isinstance(reward_model, ProcessRewardModel):  # each clause's score at its token; no EOS: the penalty at the end
        last = F.one_hot(mask.sum(1).long() - 1, mask.shape[1]) * args.no_eos_score
        clause_scores = reward_model.clause_scores(tokens, mask)
        batch["clause_scores"] = torch.where(has_eos[:, None], clause_scores, last)
        batch["clause_right"], batch["clause_ends"] = clause_right(clause_scores, tokens, mask)
        scores = batch["clause_scores"].sum(1)  # a response's score, as ProcessRewardModel.score, from the same read
    else:
        scores = torch.where(has_eos, reward_model.score(tokens, mask), args.no_eos_score)
    gold, forms = gold_scores(tokens, mask)
    batch |= {"ref_logprobs": ref_logprobs, "values": values[:, PROMPT_LENGTH - 1 : -1] * mask, "scores": scores}
    if isinstance(reward_model, Ensemble):  # each member's score [B, K]: do they agree on what pi writes?
        batch["rm_members"] = reward_model.score(tokens, mask, members=True).T
    return batch | forms | {"gold": gold, "has_eos": has_eos.float(), "entropy": dist.entropy()}


def gradient_step(agent, optimizer, loss, args):
    optimizer.zero_grad()
    loss.backward()
    nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)  # core detail 11
    optimizer.step()


def policy_loss(logits, mb, args):
    """Minus L^CLIP over a minibatch's masked tokens, from the policy's logits, and what the update logs of it."""
    mask = mb["mask"]
    dist = response_dist(logits, args.temperature)
    # Masked before exp: the log-ratio at a PAD position is 0, whatever the old log-prob stored there.
    logratio = (dist.log_prob(mb["responses"]) - mb["logprobs"]) * mask
    ratio = logratio.exp()  # r_t(theta), paper eq. (6)
    pg_loss = clipped_surrogate_loss(ratio, mb["advantages"], args.clip_coef, mask)
    # Core detail 12: approx_kl is the (r - 1) - log r estimator of KL[old, new].
    stats = {"policy_loss": pg_loss, "entropy": masked_mean(dist.entropy(), mask)}
    stats |= {"old_approx_kl": masked_mean(-logratio, mask), "approx_kl": masked_mean((ratio - 1) - logratio, mask)}
    stats["clipfrac"] = masked_mean(((ratio - 1.0).abs() > args.clip_coef).float(), mask)
    return pg_loss, stats


def ppo_update(agent, optimizer, mb, args):
    """A minibatch step on minus L^CLIP + c1 L^VF (eq. (9) without its entropy bonus), over the masked tokens only."""
    logits, newvalues = agent(mb["tokens"])
    pg_loss, stats = policy_loss(logits, mb, args)
    v_loss = value_loss(newvalues[:, PROMPT_LENGTH - 1 : -1], mb["values"], mb["returns"], args.clip_coef, mb["mask"])
    loss = pg_loss + args.vf_coef * v_loss
    gradient_step(agent, optimizer, loss, args)
    return {name: stat.detach() for name, stat in (stats | {"value_loss": v_loss, "loss": loss}).items()}


def minibatches(data, args, device):
    """K epochs over the batch `data`, each a new shuffle cut into minibatches (core detail 6)."""
    for _ in range(args.update_epochs):
        for mb_inds in torch.randperm(args.batch_size, device=device).split(args.minibatch_size):
            yield {key: value[mb_inds] for key, value in data.items()}


def train_ppo(args, sft, reward_model, checkpoint, run_dir, device, stop, writer):
    """Stage 3: PPO-Clip, with the rewards of compute_rewards: the RM's score and the KL penalty to pi_SFT. Or one of
    PPO's successors (after this path) in its update's place: a group baseline (--advantage), DPO, IPO or KTO."""
    reference = sft.requires_grad_(False)  # pi_SFT, frozen
    ppo = args.advantage == "gae" and not (args.dpo or args.kto)  # PPO's successors here fit no value function
    agent = Agent(sft, reward_model.requires_grad_(args.rm_refresh > 0), args.value_model if ppo else "policy-head")
    agent.requires_grad_(True)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)  # core detail 3
    num_iterations = args.total_episodes // args.batch_size
    checkpoint_path = os.path.join(run_dir, "checkpoint.pt")
    kl_coef = checkpoint["kl_coef"] if checkpoint else args.kl_coef
    rm_optimizer = torch.optim.Adam(reward_model.parameters(), lr=args.rm_learning_rate) if args.rm_refresh else None
    refresh_labels = checkpoint.get("refresh_labels", 0) if checkpoint else 0
    # DPO's pairs are stage 2's, drawn with stage 2's seed: before stage 3's random state is set or restored
    pairs = dpo_pairs(reference, args, device) if args.dpo or args.kto else None
    torch.manual_seed(args.seed + 2)
    if checkpoint:
        agent.load_state_dict(checkpoint["agent"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        if rm_optimizer:
            rm_optimizer.load_state_dict(checkpoint["rm_optimizer"])
        torch.set_rng_state(checkpoint["torch_rng_state"])
        print(f"resuming {run_dir} at step {checkpoint['global_step']:,} (iteration {checkpoint['iteration']})")
    if args.compile:  # in place: the calls below, and the names in the checkpoint, stay the module's
        agent.compile()
    log = Log(writer, args, checkpoint, device)

    # ALGORITHM 1, with prompts for actors: for iteration = 1, 2, ...
    for iteration in range(checkpoint["iteration"] + 1 if checkpoint else 1, num_iterations + 1):
        # ROLLOUT: a response to each prompt from pi_theta_old, scored by the reward model.
        batch = rollout(agent, reference, reward_model, args)
        global_step = iteration * args.batch_size

        # REWARDS AND ADVANTAGES: the KL penalty at every token and the score at the EOS, then GAE over tokens.
        mask = batch["mask"]
        scores = batch.get("clause_scores", batch["scores"])  # with --reward process, a score at each clause's end
        rewards = compute_rewards(scores, batch["logprobs"], batch["ref_logprobs"], mask, kl_coef)
        if ppo:
            advantages, batch["returns"] = compute_gae(rewards, batch["values"], mask, args.gamma, args.gae_lambda)
            # Whitened once over the batch's tokens; Ziegler et al.'s code, like core detail 7, whitens each minibatch.
            mean = masked_mean(advantages, mask)
            std = masked_mean((advantages - mean) ** 2, mask).sqrt()
            batch["advantages"] = (advantages - mean) / (std + 1e-8) * mask
            # UPDATE: K epochs of minibatch gradient descent, a new shuffle each epoch (core detail 6).
            update_stats = [ppo_update(agent, optimizer, mb, args) for mb in minibatches(batch, args, device)]
        elif pairs is None:  # GRPO, Dr. GRPO, RLOO (after PPO's path): a group's baseline for the critic and GAE
            update_stats = group_baseline_update(agent, optimizer, batch, rewards, args, device)
        else:  # DPO, IPO, KTO (after PPO's path): a loss on the reward model's own pairs; the rollout only measures
            update_stats = preference_update(agent, reference, optimizer, pairs, args, device)

        # LOGGING (and samples, at a checkpoint), then Ziegler et al.'s controller: beta from this iteration's KL.
        save = stop or iteration % args.save_every == 0 or iteration == num_iterations
        scalars = log.update(iteration, batch, rewards, update_stats, kl_coef, save)
        if args.adaptive_kl:
            kl_coef = adapt_kl_coef(kl_coef, scalars["rlhf/kl"], args.kl_target, args.batch_size, args.kl_horizon)
        if args.rm_refresh and iteration % args.rm_refresh == 0:  # the next rollouts are scored by the refreshed RM
            refresh_labels += refresh_reward_model(reward_model, rm_optimizer, agent.policy, args)

        # CHECKPOINT, unless the run diverged: then the last finite checkpoint stays on disk.
        if not (math.isfinite(scalars["losses/loss"]) and all(p.isfinite().all() for p in agent.parameters())):
            advice = "start a new run with a smaller --learning-rate (--resume keeps every hyperparameter)"
            raise Diverged(f"loss or weights not finite after iteration {iteration}; {advice}")
        if save or stop:
            state = dict(agent=agent.state_dict(), optimizer=optimizer.state_dict(), reference=reference.state_dict())
            state |= dict(reward_model=reward_model.state_dict(), rm_pool=log.pool, kl_coef=kl_coef)
            state |= dict(global_step=global_step, iteration=iteration, torch_rng_state=torch.get_rng_state())
            state |= dict(rm_optimizer=rm_optimizer.state_dict(), refresh_labels=refresh_labels) if rm_optimizer else {}
            save_checkpoint(checkpoint_path, "ppo", args, **state)
        if stop:
            raise Stopped(f"stopped at step {global_step:,}; continue with --resume {checkpoint_path}")
    print(f"saved {checkpoint_path}")
    return agent, run_dir


def train(args, stop=()):
    """Stages 1 to 3, each skipped where a checkpoint holds it, each stopping once `stop` is non-empty; returns (agent,
    run_dir) or raises Stopped, Diverged."""
    from torch.utils.tensorboard import SummaryWriter

    checkpoint, args = load_checkpoint(args.resume, args) if args.resume else (None, args)  # --resume: its args
    run_dir = args.run_dir or new_run_dir(args)
    device = torch.device(("cuda" if torch.cuda.is_available() else "cpu") if args.device == "auto" else args.device)
    if checkpoint:  # a resumed stage 3: stages 1 and 2 are in its checkpoint
        sft = new_model(args, device, checkpoint["reference"])
        kind = ProcessRewardModel if args.reward == "process" else TinyLM
        reward_model = new_model(args, device, checkpoint["reward_model"], args.rm_ensemble, kind)
    else:
        os.makedirs(run_dir, exist_ok=True)
        sft = train_sft(args, run_dir, device, stop)
        reward_model = train_reward_model(args, sft, run_dir, device, stop)
    # On --resume, purge_step drops what the run logged after its checkpoint: its curves go on without a fold.
    with SummaryWriter(run_dir, purge_step=checkpoint["global_step"] + 1 if checkpoint else None) as writer:
        return train_ppo(args, sft, reward_model, checkpoint, run_dir, device, stop, writer)


# PPO'S SUCCESSORS, each under its own name: GRPO, Dr. GRPO and RLOO put a group's baseline in the critic's place, DPO,
# IPO and KTO a loss on the RM's pairs in the rollouts', and an ensemble of reward models scores in the RM's.
def grpo_advantages(returns):
    """GRPO's advantage (Shao et al. 2024, arXiv:2402.03300, §4.1.2) of each response, from the summed rewards [G, K]
    of G groups of K responses to one prompt: its return minus its group's mean, over the group's std. The KL penalty
    stays in the reward, as in PPO (DeepSeek's GRPO and TRL's add it to the loss): so the division scales it too, and
    its effective beta is beta / std of the group's rewards. The loss averages over all the minibatch's tokens, as for
    PPO, where DeepSeekMath averages each response's tokens first (a bias toward short responses, Liu et al. find: Dr.
    GRPO drops it too)."""
    return (returns - returns.mean(1, keepdim=True)) / (returns.std(1, keepdim=True) + 1e-8)


def dr_grpo_advantages(returns):
    """Dr. GRPO's (Liu et al. 2025): GRPO's without the division by the std.

    >>> dr_grpo_advantages(torch.tensor([[1.0, 2.0, 6.0]])), rloo_advantages(torch.tensor([[1.0, 2.0, 6.0]]))
    (tensor([[-2., -1.,  3.]]), tensor([[-3.0000, -1.5000,  4.5000]]))
    """
    return returns - returns.mean(1, keepdim=True)


def rloo_advantages(returns):
    """RLOO's (Ahmadian et al. 2024): a response's return minus the mean of the others' in its group, Dr. GRPO's
    advantage times K / (K - 1)."""
    return returns - (returns.sum(1, keepdim=True) - returns) / (returns.shape[1] - 1)


def group_baseline_update(agent, optimizer, batch, rewards, args, device):
    """The update of --advantage grpo, dr-grpo or rloo: PPO's, with a group's baseline in the critic's place (rollout
    samples --group-size responses to each prompt) and no critic to fit: minus L^CLIP alone, and no value loss."""
    kinds = {"grpo": grpo_advantages, "dr-grpo": dr_grpo_advantages, "rloo": rloo_advantages}
    returns = rewards.sum(1).view(-1, args.group_size)  # each response's summed reward, a row for each group
    batch["advantages"] = kinds[args.advantage](returns).view(-1, 1) * batch["mask"]
    update_stats = []
    for mb in minibatches(batch, args, device):
        pg_loss, stats = policy_loss(agent(mb["tokens"])[0], mb, args)
        gradient_step(agent, optimizer, pg_loss, args)
        update_stats.append({name: stat.detach() for name, stat in (stats | {"loss": pg_loss}).items()})
    return update_stats


def sequence_logprobs(lm, tokens, mask, temperature):
    """log pi(y|x) of each whole response [B]: the sum of its tokens' log-probs."""
    return (response_dist(lm(tokens)[0], temperature).log_prob(tokens[:, PROMPT_LENGTH:]) * mask).sum(1)


def dpo_pairs(reference, args, device):
    """DPO's data: the reward model's training pairs, with pi_SFT's log-prob of each response, computed once. KTO also
    takes "kept", the pairs whose chosen response it keeps (--kto-desirable-share)."""
    tokens, mask, chosen, rejected, n_train = preference_pairs(reference, args, device)
    pairs = {"kept": torch.arange(n_train, device=device) < args.kto_desirable_share * n_train}
    for side, rows in (("chosen", chosen[:n_train]), ("rejected", rejected[:n_train])):
        pairs |= {f"{side}_tokens": tokens[rows], f"{side}_mask": mask[rows]}
        pairs[f"{side}_ref"] = sequence_logprobs(reference, tokens[rows], mask[rows], args.temperature).detach()
    return pairs


def preference_update(agent, reference, optimizer, pairs, args, device):
    """The update of --dpo (--ipo) or --kto: dpo_update on minibatches of --batch-size of the RM's pairs, drawn anew."""
    rows = torch.randint(len(pairs["chosen_ref"]), (args.batch_size,), device=device)
    data = {key: value[rows] for key, value in pairs.items()}
    mbs = (kto_mismatched(reference, mb, args) if args.kto else mb for mb in minibatches(data, args, device))
    return [dpo_update(agent, optimizer, mb, args) for mb in mbs]


def dpo_update(agent, optimizer, mb, args):
    """A minibatch step of DPO (Rafailov et al. 2023, eq. (7)): the reward model's own Bradley-Terry loss on its own
    pairs, with beta log(pi(y|x) / pi_SFT(y|x)), the reward that pi* of compute_rewards' objective implies, in place of
    the RM's score. DPO removes the reward model and the rollouts, and keeps the objective: E[r] - beta KL. With --ipo
    or --kto, ipo_loss or kto_loss on the same implied rewards."""
    implicit = {}
    for side in ("chosen", "rejected", "kl") if args.kto else ("chosen", "rejected"):
        with torch.set_grad_enabled(side != "kl"):  # KTO's mismatched pairs, for its reference point: no gradient
            logprobs = sequence_logprobs(agent.policy, mb[f"{side}_tokens"], mb[f"{side}_mask"], args.temperature)
        implicit[side] = args.kl_coef * (logprobs - mb[f"{side}_ref"])
    if args.kto:
        loss = kto_loss(implicit["chosen"][mb["kept"]], implicit["rejected"], implicit["kl"], args.kto_weights)
    elif args.ipo:
        loss = ipo_loss(implicit["chosen"], implicit["rejected"], args.kl_coef)
    else:
        loss = preference_loss(implicit["chosen"], implicit["rejected"])
    gradient_step(agent, optimizer, loss, args)
    accuracy = (implicit["chosen"] > implicit["rejected"]).float().mean()  # how often pi prefers the chosen
    stats = {"loss": loss.detach(), "policy_loss": loss.detach(), "implicit_accuracy": accuracy}
    if args.kto:  # KTO's reference point z0, and the mismatched pairs' mean implied reward, which it clamps at 0
        stats |= {"kto_z0": implicit["kl"].mean().clamp(min=0), "kto_mismatched_reward": implicit["kl"].mean()}
    return stats


def ipo_loss(chosen, rejected, beta):
    """IPO's loss (Azar et al. 2023) on the implied rewards of pairs: the log-ratio margin's squared distance from
    1 / (2 beta), a margin with a target, where DPO's loss falls as long as the margin grows, without bound."""
    return (((chosen - rejected) / beta - 1 / (2 * beta)) ** 2).mean()


def kto_loss(desirable, undesirable, mismatched, weights):
    """KTO's loss (Ethayarajh et al. 2024, eq. (8)) from the implied rewards r = beta log(pi(y|x) / pi_SFT(y|x)) of
    responses judged alone: lambda_D (1 - sigmoid(r - z0)) for a desirable one, lambda_U (1 - sigmoid(z0 - r)) for an
    undesirable one, averaged over both. z0, the reference point, stands for beta KL[pi || pi_SFT]; TRL's KTOTrainer
    estimates it as the mismatched pairs' mean implied reward (kto_mismatched), clamped at 0, and held constant. Those
    responses are pi_SFT's samples, not pi's: their mean estimates about -beta KL[pi_SFT || pi] <= 0, so z0 stays near
    0, and the loss is in effect TRL's apo_zero_unpaired, r against 0.

    >>> kto_loss(torch.zeros(1), torch.zeros(2), torch.zeros(1), (1.0, 2.0))  # (1 x 0.5 + 2 x 2 x 0.5) / 3
    tensor(0.8333)
    """
    z0 = mismatched.mean().clamp(min=0)
    losses = [weights[0] * (1 - torch.sigmoid(desirable - z0)), weights[1] * (1 - torch.sigmoid(z0 - undesirable))]
    return torch.cat(losses).mean()


def kto_mismatched(reference, mb, args):
    """KTO's mismatched pairs for z0 (kto_loss), as TRL's KTOTrainer builds them: the minibatch's own responses (the
    kept desirable, the undesirable) rotated by one, each after another pair's prompt; with pi_SFT's log-prob."""
    tokens = torch.cat([mb["chosen_tokens"][mb["kept"]], mb["rejected_tokens"]])
    mask = torch.cat([mb["chosen_mask"][mb["kept"]], mb["rejected_mask"]]).roll(1, 0)
    tokens = torch.cat([tokens[:, :PROMPT_LENGTH], tokens[:, PROMPT_LENGTH:].roll(1, 0)], 1)
    kl_ref = sequence_logprobs(reference, tokens, mask, args.temperature)
    return mb | {"kl_tokens": tokens, "kl_mask": mask, "kl_ref": kl_ref}


class Ensemble(nn.ModuleList):
    """--rm-ensemble K reward models as one (Coste et al. 2023): the mean of their scores, the minimum (worst case), or
    uwo, the mean minus lambda times their variance (uncertainty-weighted). members=True: each member's [K, B]."""

    def __init__(self, members, args):
        super().__init__(members)
        self.args = args

    def score(self, tokens, mask, members=False):
        scores = torch.stack([reward_model.score(tokens, mask) for reward_model in self])
        aggregates = {"mean": scores.mean(0), "min": scores.min(0).values}
        aggregates["uwo"] = scores.mean(0) - self.args.uwo_coef * scores.var(0)
        return scores if members else aggregates[self.args.rm_ensemble_agg]


# MACHINERY: what running the algorithm takes, and teaches nothing of it: how a run ends early (Stopped by Ctrl-C or
# SIGTERM, after a checkpoint, or Diverged, the last finite one kept), logs, checkpoints, argument checks, main().
class Stopped(Exception): ...


class Diverged(Exception): ...


def report(stage, done, total, start, text, first=0):
    """A progress line at each tenth of a stage and at its end, with the stage's ETA."""
    if done % max(total // 10, 1) == 0 or done == total:
        eta = (total - done) * (time.time() - start) / max(done - first, 1) / 60
        print(f"{stage} {done:,}/{total:,} | {text} | ETA {eta:.1f} min", flush=True)


class Log:
    """Stage 3's TensorBoard scalars and progress lines, and its pool: (RM score, gold, prompt) of the last POOL
    responses, whose pairs measure the RM's accuracy (a checkpoint keeps it; an older one's, without prompts, not)."""

    def __init__(self, writer, args, checkpoint, device):
        table = "\n".join(f"|{k}|{v}|" for k, v in asdict(args).items())
        writer.add_text("hyperparameters", "|param|value|\n|-|-|\n" + table)
        self.writer = writer
        self.args = args
        self.done = checkpoint["iteration"] if checkpoint else 0  # the iterations done before this process
        resumed = checkpoint and len(checkpoint["rm_pool"]) == 3
        self.pool = checkpoint["rm_pool"].to(device) if resumed else torch.zeros(3, 0, device=device)
        self.start_time = time.time()

    def update(self, iteration, batch, rewards, update_stats, kl_coef, save):
        losses = {name: torch.stack([stats[name] for stats in update_stats]).mean().item() for name in update_stats[0]}
        if "returns" in batch:  # a critic was fitted
            returns, values = (batch[key][batch["mask"].bool()] for key in ("returns", "values"))
            losses["explained_variance"] = (1 - (returns - values).var() / returns.var()).item()
        prompts = (batch["tokens"][:, 2] * len(WORDS) + batch["tokens"][:, 4]).float()  # its NOUN and ADJ, one number
        self.pool = torch.cat([self.pool, torch.stack([batch["scores"], batch["gold"], prompts])], 1)[:, -POOL:]
        stats = response_stats(batch, self.pool)
        sps = (iteration - self.done) * self.args.batch_size / (time.time() - self.start_time)
        scalars = {f"losses/{name}": value for name, value in losses.items()} | stats | {"rlhf/kl_coef": kl_coef}
        scalars |= {"charts/SPS": sps, "charts/learning_rate": self.args.learning_rate}
        scalars["charts/episodic_return"] = rewards.sum(1).mean().item()
        scalars["charts/episodic_length"] = stats["rlhf/response_length"]
        for name, value in scalars.items():
            self.writer.add_scalar(name, value, iteration * self.args.batch_size)
        names = ("score", "gold_score", "kl", "rm_accuracy")
        text = " | ".join(f"{name} {stats[f'rlhf/{name}']:+.2f}" for name in names)
        stage = f"stage 3, {'KTO' if self.args.kto else 'DPO' if self.args.dpo else 'PPO'}: iteration"
        text = f"{text} | beta {kl_coef:.3g} | SPS {sps:.0f}"
        report(stage, iteration, self.args.total_episodes // self.args.batch_size, self.start_time, text, self.done)
        if save:  # the responses the RM scores highest, which pi is pulled toward, beside their gold
            for i in batch["scores"].argsort(descending=True)[:3].tolist():
                text = " ".join(WORDS[t] for t in batch["tokens"][i].tolist() if t not in (PAD, BOS))
                print(f"  score {batch['scores'][i]:+.2f} | gold {batch['gold'][i]:+3.0f} | {text}")
            self.writer.flush()  # the curve on disk reaches at least the checkpoint's step
        return scalars


def response_stats(batch, pool):
    """What a batch of responses shows: its scores, its KL to pi_SFT (per response, in nats), its forms; and how often
    the RM ranks as gold does the pairs in `pool`, (RM scores, gold, prompts) of the policy's recent responses."""
    mask = batch["mask"]
    stats = {"score": batch["scores"].mean(), "gold_score": batch["gold"].mean()}
    stats["kl"] = ((batch["logprobs"] - batch["ref_logprobs"]) * mask).sum(1).mean()
    stats |= {name: batch[name].mean() for name in ("well_formed", "spam", "garbled")}
    stats["entropy"] = masked_mean(batch["entropy"], mask)
    stats |= {"response_length": mask.sum(1).mean(), "eos_fraction": batch["has_eos"].mean()}
    stats["rm_accuracy"], stats["rm_pairs"] = pairwise_accuracy(*pool)
    if "clause_right" in batch:  # a process RM: how often it rates the policy's clauses as gold does
        stats["rm_clause_accuracy"] = batch["clause_right"].sum() / batch["clause_ends"].sum()
    if "rm_members" in batch:  # an ensemble's members, each's mean score, and their disagreement (their std)
        stats |= {f"rm_member{k}": score.mean() for k, score in enumerate(batch["rm_members"].T)}
        stats["rm_disagreement"] = batch["rm_members"].std(1).mean()
    return {f"rlhf/{name}": value.item() for name, value in stats.items()}


# Typed with --resume, a runtime flag (how the run goes on, where it logs) applies; another field of Args is refused.
RUNTIME_FIELDS = "device compile torch_threads save_every resume".split()
RUNTIME_FIELDS += "run_dir exp_name track wandb_project_name wandb_entity".split()
FORMAT = "ppo-checkpoint-v1"


def save_checkpoint(path, stage, args, **state):
    # Tensors, numbers and strings, loadable with torch.load(weights_only=True); written, then renamed, atomically.
    torch.save({"format": FORMAT, "script": SCRIPT, "stage": stage, "args": asdict(args), **state}, f"{path}.tmp")
    os.replace(f"{path}.tmp", path)


def load_checkpoint(path, args, stage="ppo"):
    """A checkpoint of this script's `stage` on the CPU, and the Args of its run (a field it lacks takes its default),
    with RUNTIME_FIELDS from `args` and its folder for run_dir; else a one-line ValueError."""
    if not os.path.isfile(path):
        raise ValueError(f"checkpoint {path!r} does not exist")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:
        raise ValueError(f"cannot read checkpoint {path!r}: it is corrupt or not a checkpoint") from None
    if not isinstance(checkpoint, dict) or (checkpoint.get("format"), checkpoint.get("script")) != (FORMAT, SCRIPT):
        raise ValueError(f"{path!r} is not a checkpoint written by {SCRIPT} or a copy of it")
    if checkpoint.get("stage") != stage:
        raise ValueError(f"{path!r} is a checkpoint of the {checkpoint.get('stage')} stage, not of the {stage} stage")
    unknown = set(checkpoint["args"]) - set(asdict(args))  # a field renamed or removed since the checkpoint
    if unknown:
        raise ValueError(f"{path!r} holds hyperparameters that this script's Args lacks: {', '.join(sorted(unknown))}")
    runtime = {key: getattr(args, key) for key in RUNTIME_FIELDS}
    run_dir = args.run_dir or os.path.dirname(os.path.abspath(path))  # by default, the checkpoint's folder
    return checkpoint, Args(**{**checkpoint["args"], **runtime, "run_dir": run_dir})


def check_network(model, saved, path):
    """Refuse weights saved by another network, in one line that names the first parameter that differs."""
    shapes = [[f"{k} {list(v.shape)}" for k, v in d.items() if torch.is_tensor(v)] for d in (saved, model.state_dict())]
    for theirs, mine in itertools.zip_longest(*shapes, fillvalue="nothing"):
        if theirs != mine:
            raise ValueError(f"{path!r} holds another network: {theirs} where this script's has {mine}")


# Every number must be finite. These must also be positive, and these lie in ranges of their own; a number that is in
# neither list (a new flag, say) may take any finite value.
POSITIVE = "torch_threads d_model n_layer n_head temperature sft_steps sft_batch_size sft_learning_rate".split()
POSITIVE += "rm_epochs rm_batch_size rm_learning_rate rm_ensemble total_episodes batch_size minibatch_size".split()
POSITIVE += "update_epochs learning_rate kl_target kl_horizon clip_coef max_grad_norm save_every".split()
# The shortest response, "the NOUN was ADJ <eos>", is 5 tokens; 100 comparisons hold out 10 to measure the RM with.
RANGES = {"gamma": (0, 1), "gae_lambda": (0, 1), "kto_desirable_share": (0, 1), "rm_pairs": (100, math.inf)}
RANGES |= {"kl_coef": (0, math.inf), "vf_coef": (0, math.inf), "uwo_coef": (0, math.inf), "group_size": (2, math.inf)}
RANGES |= {"response_length": (5, BLOCK_SIZE - PROMPT_LENGTH), "rm_refresh": (0, math.inf)}


def check_args(args):
    """Reject bad input before anything heavy loads, with a one-line reason (a ValueError)."""
    flag = lambda name: "--" + name.replace("_", "-")  # noqa: E731
    for name, value in asdict(args).items():
        low, high = RANGES.get(name, (-math.inf, math.inf))
        if type(value) not in (int, float):  # strings, booleans and None have no range
            continue
        if not math.isfinite(value):
            raise ValueError(f"{flag(name)} must be a finite number, got {value}")
        if name in POSITIVE and value <= 0:
            raise ValueError(f"{flag(name)} must be positive, got {value}")
        if not low <= value <= high:
            raise ValueError(f"{flag(name)} must be in [{low}, {high}], got {value}")
    grpo = [] if args.advantage == "gae" else [("group_size", "batch_size")]
    for name, whole in [("n_head", "d_model"), ("minibatch_size", "batch_size"), *grpo]:
        if getattr(args, whole) % getattr(args, name):
            raise ValueError(f"{flag(name)} {getattr(args, name)} does not divide {flag(whole)} {getattr(args, whole)}")
    if args.dpo and args.kto:
        raise ValueError("--dpo and --kto are two losses of stage 3: take one")
    if (args.dpo or args.kto) and (args.adaptive_kl or args.kl_coef == 0 or args.advantage != "gae"):
        raise ValueError("--dpo and --kto take their beta from a positive, fixed --kl-coef, and have no --advantage")
    if not all(math.isfinite(weight) and weight > 0 for weight in args.kto_weights):
        raise ValueError(f"--kto-weights must be two positive numbers, got {args.kto_weights}")
    if args.ipo and not args.dpo:
        raise ValueError("--ipo is a loss of --dpo: add --dpo")
    if args.reward == "process" and args.rm_ensemble > 1:
        raise ValueError("--reward process trains one process reward model: drop --rm-ensemble")
    if args.rm_refresh and (args.rm_ensemble > 1 or args.dpo or args.kto):
        raise ValueError("--rm-refresh trains the one reward model PPO reads: drop --rm-ensemble, --dpo and --kto")
    if args.rm_same_head and args.rm_ensemble == 1:
        raise ValueError("--rm-same-head is how the members of an ensemble start: add --rm-ensemble K > 1")
    if args.adaptive_kl and args.kl_coef == 0:
        raise ValueError("--adaptive-kl needs a positive --kl-coef to start from: it scales beta, and 0 stays 0")
    if args.total_episodes < args.batch_size:
        raise ValueError(f"--total-episodes {args.total_episodes} is less than one batch of {args.batch_size}")
    if args.device not in ("auto", "cpu") and not (args.device.startswith("cuda") and torch.cuda.is_available()):
        raise ValueError(f"--device {args.device} is not available here; use auto or cpu")
    existing = os.path.abspath(args.run_dir or ".")
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing) or not os.access(existing, os.W_OK):
        raise ValueError(f"--run-dir {args.run_dir} cannot be created or written: {existing} is a file or read-only")
    held = args.run_dir and os.path.isdir(args.run_dir) and os.listdir(args.run_dir)
    if args.resume is None and held and any("tfevents" in f or f.endswith(".pt") for f in held):
        path = os.path.join(args.run_dir, "checkpoint.pt")
        raise ValueError(f"--run-dir {args.run_dir} already holds a run: continue it with --resume {path}")
    # Networks of other shapes (other flags, a copy's code) are refused before anything is written; --resume's has both
    kind = ProcessRewardModel if args.reward == "process" else TinyLM
    networks = {"sft": new_model(args, "cpu"), "reward_model": new_model(args, "cpu", None, args.rm_ensemble, kind)}
    for stage, path in [("sft", args.sft_checkpoint), ("reward_model", args.reward_model_checkpoint)]:
        if args.resume or path:
            saved = load_checkpoint(args.resume or path, args, "ppo" if args.resume else stage)[0]
            state = saved["reference" if stage == "sft" else stage] if args.resume else saved["model"]
            check_network(networks[stage], state, args.resume or path)


def new_run_dir(args):
    """Make runs/reviews__{exp_name}__{seed}__{time}, or, if a run started in the same second has it, the next free
    name (...-2, -3, ...): mkdir is atomic, so no two runs share one."""
    base = f"runs/reviews__{args.exp_name}__{args.seed}__{int(time.time())}"
    for name in itertools.chain([base], (f"{base}-{clash}" for clash in itertools.count(2))):
        with contextlib.suppress(FileExistsError):  # the name is taken: try the next
            os.makedirs(name)
            return name


def start_tracking(args):
    """--track: a Weights & Biases run, named after the run directory so that --resume continues it, mirrors the
    TensorBoard scalars. With no login or no network, it logs offline for `wandb sync` to upload."""
    import wandb

    args.run_dir = args.run_dir or new_run_dir(args)  # train() writes there too
    name = os.path.basename(os.path.abspath(args.run_dir))
    init = dict(project=args.wandb_project_name, entity=args.wandb_entity, name=name, id=name, config=asdict(args))
    init |= dict(sync_tensorboard=True, save_code=True, resume="allow")
    try:
        wandb.init(**init)
    except wandb.Error as e:  # no login, or no answer within W&B's timeout: training goes on, logged offline
        print(f"wandb: {e}: logging offline instead, for `wandb sync` to upload", file=sys.stderr)
        wandb.teardown()
        wandb.init(**init, mode="offline")


def main():
    import tyro

    args = tyro.cli(Args)
    try:
        if args.resume:  # the command line read again over the checkpoint's hyperparameters shows what was typed
            saved = load_checkpoint(args.resume, args)[1]
            args = tyro.cli(Args, default=saved)
            typed = [f"--{k.replace('_', '-')} {v}" for k, v in asdict(args).items() if v != getattr(saved, k)]
            if typed:  # never dropped in silence
                raise ValueError(f"{', '.join(typed)}: a resumed run keeps its checkpoint's hyperparameters")
        check_args(args)
    except ValueError as e:
        print(f"{SCRIPT}: error: {e}", file=sys.stderr)  # one line, before anything starts
        sys.exit(2)
    torch.set_num_threads(args.torch_threads)
    if args.track:  # W&B's run, and its patch of TensorBoard's writer, belong to the process: main() starts them
        start_tracking(args)
    # A training run owns the process: Ctrl-C and SIGTERM only set the flag that each stage reads after each step.
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))
    try:
        train(args, stop)
    except Stopped as e:
        print(e)
        sys.exit(130)
    except Diverged as e:
        print(f"{SCRIPT}: error: {e}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
