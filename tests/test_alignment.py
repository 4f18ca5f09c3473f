"""The scripts are deliberate copies. What they share must stay word for word the same, so that
`diff` between two scripts shows a learner only what the variant changes."""

import ast
import itertools

import pytest
from conftest import ROOT, SCRIPTS

# Top-level definitions that a variant is meant to change.
CHANGED_ON_PURPOSE = {
    ("ppo_continuous.py", "ppo_kl_penalty.py"): {"Args", "make_checkpoint", "check_args", "train"},
    # The Atari script has its own envs, network, rollout and evaluation; the math, the
    # checkpoint format and the command line are shared.
    ("ppo_atari.py", "ppo_continuous.py"): {"Args", "make_envs", "Agent", "check_args", "train", "evaluate"},
}
MUST_SHARE = {
    ("ppo_continuous.py", "ppo_kl_penalty.py"): {"compute_gae", "value_loss", "RunningMeanStd", "Agent", "load_checkpoint", "evaluate"},
    ("ppo_atari.py", "ppo_continuous.py"): {"compute_gae", "clipped_surrogate_loss", "value_loss", "layer_init", "make_checkpoint",
                                            "save_checkpoint", "load_checkpoint", "args_from_checkpoint", "main"},
}  # fmt: skip


def top_level_sources(script):
    source = (ROOT / script).read_text()
    tree = ast.parse(source)
    return {
        node.name: ast.get_source_segment(source, node)
        for node in tree.body
        if isinstance(node, (ast.FunctionDef, ast.ClassDef))
    }


@pytest.mark.parametrize("pair", list(itertools.combinations(SCRIPTS, 2)), ids="-vs-".join)
def test_shared_definitions_are_identical(pair):
    if pair not in CHANGED_ON_PURPOSE:
        pytest.skip(f"{pair} are not variants of one another")
    a, b = (top_level_sources(s) for s in pair)
    shared = (set(a) & set(b)) - CHANGED_ON_PURPOSE[pair]
    assert MUST_SHARE[pair] <= shared, MUST_SHARE[pair] - shared
    drifted = sorted(name for name in shared if a[name] != b[name])
    assert not drifted, f"{drifted} differ between {pair[0]} and {pair[1]}"
