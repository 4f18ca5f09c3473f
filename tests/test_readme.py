"""The README's tables and commands are checked against the code, so they cannot go stale."""

import dataclasses
import re

from conftest import ROOT, load_script
from test_cli import EXPECTED_SCALARS

README = (ROOT / "README.md").read_text()
DETAIL_MENTION = re.compile(r"(?i)\b(core|continuous|atari) details? (\d+(?:\s*[-,/]\s*\d+)*)")


def mentioned_details(line):
    """The (family, number) pairs a source line's comment cites, e.g. 'continuous details 8-9'."""
    found = set()
    for family, spec in DETAIL_MENTION.findall(line):
        for part in re.split(r"\s*[,/]\s*", spec):
            lo, _, hi = part.partition("-")
            found |= {(family.lower(), n) for n in range(int(lo), int(hi or lo) + 1)}
    return found


def test_every_detail_links_to_a_line_that_cites_it():
    rows = re.findall(r"^\| (core|continuous|atari) (\d+) \|.*\]\((ppo_\w+\.py)#L(\d+)\) \|$", README, re.M)
    expected = {("core", n) for n in range(1, 14)} | {("continuous", n) for n in range(1, 10)} | {("atari", n) for n in range(1, 10)}
    assert {(f, int(n)) for f, n, _, _ in rows} == expected
    for family, number, script, line in rows:
        source = (ROOT / script).read_text().splitlines()
        cited_at = [i + 1 for i, text in enumerate(source) if (family, int(number)) in mentioned_details(text)]
        assert (family, int(number)) in mentioned_details(source[int(line) - 1]), (
            f"README links {family} detail {number} to {script} line {line}, but it is cited at lines {cited_at}"
        )


def test_flag_table_lists_every_flag():
    table = README.split("## Flags of `ppo_continuous.py`")[1].split("\n## ")[0]
    listed = set(re.findall(r"^\| `(--[\w-]+)`", table, re.M))
    flags = {"--" + f.name.replace("_", "-") for f in dataclasses.fields(load_script("ppo_continuous.py").Args)}
    assert listed == flags, (flags - listed, listed - flags)


def test_metrics_glossary_lists_every_scalar():
    for tag in EXPECTED_SCALARS:
        assert f"`{tag}`" in README, tag


def test_readme_test_command_is_what_ci_runs():
    command = "python -m pytest -n 2 tests"
    assert command in README
    assert command in (ROOT / ".ci" / "run").read_text()


def test_kl_flags_are_documented():
    section = README.split("## `ppo_kl_penalty.py`")[1].split("\n## ")[0]
    base = {f.name for f in dataclasses.fields(load_script("ppo_continuous.py").Args)}
    extra = {"--" + f.name.replace("_", "-") for f in dataclasses.fields(load_script("ppo_kl_penalty.py").Args) if f.name not in base}
    listed = set(re.findall(r"^\| `(--[\w-]+)`", section, re.M))
    assert listed == extra, (extra - listed, listed - extra)


def test_quoted_results_come_from_the_generated_tables():
    # Every bold figure in the README must appear in a generated table.
    sections = README
    generated = "".join(p.read_text() for p in (ROOT / "benchmarks" / "results").rglob("*.md"))
    quoted = re.findall(r"\*\*([\d.,±× ]+?)\*\*", sections)
    assert quoted
    for figure in quoted:
        for number in re.findall(r"\d[\d.]*", figure.replace(",", "")):
            assert number in generated, f"README quotes {number}, which no generated table in benchmarks/results has"
