"""The README's tables and commands are checked against the code, so they cannot go stale."""

import dataclasses
import re
import sys

import pytest
from conftest import EXPECTED_SCALARS, ROOT, SCRIPTS, load_script

README = (ROOT / "README.md").read_text()
sys.path.insert(0, str(ROOT / "benchmarks"))
import details  # noqa: E402
from details import cited_details  # noqa: E402


def test_readme_is_short():
    # About 250: the RLHF section (issues 29, 40: its GRPO arm and what the suite shows) and Figure 3 (issue 41);
    # then Table 4's command, the humanoid's result with a frame of its video, --track and `uv run` (issues 48, 50).
    assert len(README.splitlines()) <= 285


def test_every_detail_links_to_a_line_that_cites_it():
    rows = re.findall(
        r"^\| (core|continuous|atari) (\d+) \|.*\[(ppo_\w+\.py L\d+)\]\((ppo_\w+\.py)#L(\d+)\) \|$", README, re.M
    )
    expected = (
        {("core", n) for n in range(1, 14)}
        | {("continuous", n) for n in range(1, 10)}
        | {("atari", n) for n in range(1, 10)}
    )
    assert {(f, int(n)) for f, n, _, _, _ in rows} == expected
    for family, number, link_text, script, line in rows:
        assert link_text == f"{script} L{line}", (
            f"README's link text {link_text!r} does not say the line it goes to, {script}#L{line}"
        )
        source = (ROOT / script).read_text().splitlines()
        cited_at = [i + 1 for i, text in enumerate(source) if (family, int(number)) in cited_details(text)]
        assert (family, int(number)) in cited_details(source[int(line) - 1]), (
            f"README links {family} detail {number} to {script} line {line}, but it is cited at lines {cited_at}"
        )


def test_details_table_is_generated_from_the_scripts():
    # `python benchmarks/report.py` regenerates it, so that a reformat of a script moves its links too.
    assert details.details_block() in README, "run python benchmarks/report.py"
    assert cited_details("# Continuous details 8-9 and core detail 3") == {
        ("continuous", 8),
        ("continuous", 9),
        ("core", 3),
    }


def test_every_flag_the_readme_names_exists():
    flags = {"--" + f.name.replace("_", "-") for s in SCRIPTS for f in dataclasses.fields(load_script(s).Args)}
    flags |= {"--no-" + f[2:] for f in flags} | {"--help"}
    named = set(re.findall(r"`(--[a-z][\w-]*)", README)) | set(
        re.findall(r"python ppo_\w+\.py[^\n`#]*?(--[a-z][\w-]*)", README)
    )
    for command in re.findall(r"^python (ppo_\w+\.py) (.*?)(?:#|$)", README, re.M):
        named |= set(re.findall(r"--[a-z][\w-]*", command[1]))
    assert named and named <= flags, named - flags


def test_kl_flags_are_documented():
    base = {f.name for f in dataclasses.fields(load_script("ppo_continuous.py").Args)}
    extra = {
        "--" + f.name.replace("_", "-")
        for f in dataclasses.fields(load_script("ppo_kl_penalty.py").Args)
        if f.name not in base
    }
    assert extra == {"--kl-target", "--init-beta", "--adaptive-beta"}
    for flag in extra:  # each in a row of the flag table for the KL script
        assert re.search(rf"^\| [^|]*`{flag}`[^|]* \| KL \|", README, re.M), flag


def test_metrics_glossary_lists_every_scalar():
    rlhf = {
        f"rlhf/{name}"
        for name in (
            "score gold_score kl kl_coef entropy response_length eos_fraction well_formed spam garbled rm_accuracy"
            " rm_pairs"
        ).split()
    }
    for tag in EXPECTED_SCALARS | {"losses/beta", "losses/kl", "charts/clip_coef"} | rlhf:
        assert f"`{tag}`" in README, tag


def test_readme_test_command_is_what_ci_runs():
    command = "python -m pytest -n 2 tests"
    assert command in README
    assert command in (ROOT / ".ci" / "run").read_text()


NUMBER = re.compile(r"(?<![\w.])[-−]?\d[\d,]*(?:\.\d+)?(?![\w.]*\d)")


def numbers(text):
    """The numbers written in a text, as they are written (1,821 and 1821 are different figures)."""
    return {n.replace("−", "-") for n in NUMBER.findall(text)}


def figures_not_generated(readme, generated):
    """The bold figures of a README that no generated table contains, number for number."""
    quoted = [bold for bold in re.findall(r"\*\*(.+?)\*\*", readme) if re.search(r"\d", bold)]
    known = numbers(generated)
    return [n for figure in quoted for n in numbers(figure) if n not in known]


def unbolded_results(readme):
    """Mean ± spread figures typed outside bold and outside the generated blocks: quoted, but not checked."""
    typed = re.sub(r"<!-- ([\w ]+): generated.*?<!-- end of \1 -->", "", readme, flags=re.S)
    return re.findall(r"[-+−]?\d(?:[\d,.]*\d)? ± \d(?:[\d,.]*\d)?", re.sub(r"\*\*.+?\*\*", "", typed))


def test_the_figure_check_can_fail():
    generated = "| Hopper | 2,449 ± 719 | 1.74x |"
    assert figures_not_generated("We reach **2,449** at **1.74×**, **both** in 2024.", generated) == []
    assert figures_not_generated("We reach **2,44** or **449** or **2,450**.", generated) == ["2,44", "449", "2,450"]
    block = "<!-- results: generated by report.py -->\n2,449 ± 719\n<!-- end of results -->"
    assert unbolded_results(f"{block} We reach **2,449 ± 719**, a mean ± std.") == []
    assert unbolded_results(f"{block} We reach +2,449 ± 719.") == ["+2,449 ± 719"]


@pytest.mark.parametrize("path", ["README.md", "benchmarks/README.md"])
def test_quoted_figures_come_from_the_generated_tables(path):
    text = (ROOT / path).read_text()
    generated = "".join(p.read_text() for p in (ROOT / "benchmarks" / "results").rglob("*.md"))
    assert figures_not_generated(text, generated) == []
    assert unbolded_results(text) == [], "quote a result in bold, so that it is checked against the generated tables"


@pytest.mark.parametrize("path", ["README.md", "benchmarks/README.md"])
def test_every_relative_link_and_image_resolves(path):
    """A link is relative to the file that holds it, as GitHub renders it: benchmarks/README.md links results/..."""
    readme = ROOT / path
    targets = re.findall(r"\]\(([^)\s]+)\)|src=\"([^\"]+)\"", readme.read_text())
    relative = {t.split("#")[0] for pair in targets for t in pair if t and not re.match(r"[a-z]+:|#", t)}
    assert relative, "no links found: the pattern is wrong"
    assert sorted(t for t in relative if not (readme.parent / t).exists()) == []
