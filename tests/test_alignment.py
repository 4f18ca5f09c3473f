"""The scripts are deliberate copies. What they share must stay word for word the same, so that
`diff` between two scripts shows a learner only what the variant changes."""

import ast
import difflib
import doctest
import itertools

import pytest
from conftest import ROOT, SCRIPTS, load_script

# Top-level definitions that a variant is meant to change.
CHANGED_ON_PURPOSE = {
    ("ppo_continuous.py", "ppo_kl_penalty.py"): {"Args", "minibatch_loss", "save_checkpoint", "check_args", "train"},
    # Atari has its own envs, network, rollout and evaluation, and anneals L^CLIP's clip range (minibatch_loss takes
    # it); the rest of the math, checkpoints and command line are shared.
    ("ppo_atari.py", "ppo_continuous.py"): {
        "Args",
        "minibatch_loss",
        "make_envs",
        "Agent",
        "pick_device",
        "check_args",
        "train",
        "evaluate",
    },
}
# Everything below # MACHINERY that the scripts share: how a run ends early, its log, checkpoints and command line.
MACHINERY = {"Stopped", "Diverged", "Log", "load_checkpoint", "check_network", "main"}
MUST_SHARE = {
    ("ppo_continuous.py", "ppo_kl_penalty.py"): {
        "compute_gae",
        "value_loss",
        "make_env",
        "make_envs",
        "layer_init",
        "mlp",
        "RunningMeanStd",
        "Agent",
        "evaluate",
        "pick_device",
        *MACHINERY,
    },
    ("ppo_atari.py", "ppo_continuous.py"): {
        "compute_gae",
        "clipped_surrogate_loss",
        "value_loss",
        "layer_init",
        "save_checkpoint",
        *MACHINERY,
    },
}
# The lines of train() that one script of a pair has and the other lacks (difflib, non-blank, non-comment lines): what
# the variant changes, and no more. A ratio would loosen as train() shrinks; these are counts.
# Table 4's log std schedule and KL-adaptive step size are 8 lines of ppo_continuous.py's train() alone.
# Under torchrun, Atari has no normalizers to merge after the rollout and films on rank 0 only (3 lines),
# and the KL penalty's batch KL is over every rank's share (1 line).
TRAIN_DIFF = {("ppo_atari.py", "ppo_continuous.py"): 46 + 8 + 3, ("ppo_continuous.py", "ppo_kl_penalty.py"): 17 + 8 + 1}
# The lesson first: the math, Algorithm 1 in train(), the network and the envs it uses; then, under one heading, what
# running it takes (many processes, evaluation, logs, checkpoints, argument checks, main()).
SECTIONS = ["# THE MATH", "# TRAINING", "# AGENT", "# ENVIRONMENT", "# MACHINERY"]


def top_level_sources(script):
    source = (ROOT / script).read_text()
    tree = ast.parse(source)
    return {
        node.name: ast.get_source_segment(source, node)
        for node in tree.body
        if isinstance(node, (ast.FunctionDef, ast.ClassDef))
    }


def train_lines(script):
    code = [line.strip() for line in top_level_sources(script)["train"].splitlines()]
    return [line for line in code if line and not line.startswith("#")]


def differing_lines(a, b):
    matched = sum(block.size for block in difflib.SequenceMatcher(None, a, b, autojunk=False).get_matching_blocks())
    return len(a) + len(b) - 2 * matched


PAIRS = [pair for pair in itertools.combinations(SCRIPTS, 2) if pair in CHANGED_ON_PURPOSE]


def test_every_sibling_pair_is_checked():
    assert set(PAIRS) == set(CHANGED_ON_PURPOSE) == set(TRAIN_DIFF)


@pytest.mark.parametrize("pair", PAIRS, ids="-vs-".join)
def test_shared_definitions_are_identical(pair):
    a, b = (top_level_sources(s) for s in pair)
    shared = (set(a) & set(b)) - CHANGED_ON_PURPOSE[pair]
    assert MUST_SHARE[pair] <= shared, MUST_SHARE[pair] - shared
    drifted = sorted(name for name in shared if a[name] != b[name])
    assert not drifted, f"{drifted} differ between {pair[0]} and {pair[1]}"


@pytest.mark.parametrize("pair", PAIRS, ids="-vs-".join)
def test_train_stays_a_minimal_diff(pair):
    differing = differing_lines(*(train_lines(s) for s in pair))
    assert differing <= TRAIN_DIFF[pair], f"train() of {pair[0]} and {pair[1]} differ in {differing} lines"


def test_the_diff_measure_can_fail():
    assert differing_lines(["a", "b", "c", "d"], ["a", "b", "x", "y", "z"]) == 5


@pytest.mark.parametrize("script", SCRIPTS)
def test_sections_come_in_the_same_order(script):
    source = (ROOT / script).read_text()
    names = list(top_level_sources(script))
    # ppo_rlhf.py has no env to step a saved policy in, so no `evaluate`, and sections of its own before its
    # MACHINERY; the gym scripts share theirs.
    sections = SECTIONS if script != "ppo_rlhf.py" else ["# THE MATH", "# MACHINERY"]
    assert ("evaluate" in names) == (script != "ppo_rlhf.py")
    positions = [source.find(f"\n{section}") for section in sections]
    assert -1 not in positions and positions == sorted(positions), dict(zip(sections, positions, strict=True))
    order = ["Args", "compute_gae", "train", "Agent", "evaluate", "load_checkpoint", "check_args", "main"]
    if script == "ppo_rlhf.py":
        order = ["Args", "compute_gae", "train_ppo", "load_checkpoint", "check_args", "main"]
    indices = [names.index(name) for name in order]
    assert indices == sorted(indices), indices
    machinery = source.find("\n# MACHINERY")
    assert all(source.find(f"\ndef {name}(") < machinery for name in ("train", "compute_gae")), "the lesson first"


@pytest.mark.parametrize("script", SCRIPTS)
def test_doctests_pass(script):
    # The worked examples in the docstrings are checked, as `pytest --doctest-modules` over the scripts would.
    result = doctest.testmod(load_script(script), verbose=False)
    assert result.attempted >= 2 and result.failed == 0, result
