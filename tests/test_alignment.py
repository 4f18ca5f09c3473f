"""The scripts are deliberate copies. What they share must stay word for word the same, so that
`diff` between two scripts shows a learner only what the variant changes."""

import ast
import itertools

import pytest
from conftest import ROOT, SCRIPTS

# Top-level definitions that a variant is meant to change.
CHANGED_ON_PURPOSE = {
    ("ppo_continuous.py", "ppo_kl_penalty.py"): {"Args", "make_checkpoint", "check_args", "train"},
}


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
    assert {"compute_gae", "value_loss", "RunningMeanStd", "Agent", "load_checkpoint", "evaluate"} <= shared
    drifted = sorted(name for name in shared if a[name] != b[name])
    assert not drifted, f"{drifted} differ between {pair[0]} and {pair[1]}"
