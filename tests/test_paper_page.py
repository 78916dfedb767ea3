"""docs/paper.md against the results file its command writes (benchmarks/results/paper/results.json).

The page's tables are generated (`python benchmarks/paper/reproduce.py --page-only`): each block between
``<!-- paper:begin NAME -->`` and ``<!-- paper:end NAME -->`` must be exactly what the results file renders, every
claim must carry its verdict, and a number written outside the blocks must repeat one of theirs. No experiment runs.
"""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "paper.md"
RESULTS = ROOT / "benchmarks" / "results" / "paper" / "results.json"
CLAIMS = ("latency", "hybrid", "rc_sweep", "scenes", "control")
NUMBER = re.compile(r"(?<![\w.])[-+−]?\d+\.\d+")

sys.path.insert(0, str(ROOT / "benchmarks" / "paper"))  # the reproduction's modules: a script's, not the package's
import paper_numbers  # noqa: E402
import paper_page  # noqa: E402


@pytest.fixture(scope="module")
def results() -> dict:
    return json.loads(RESULTS.read_text())


def block_mismatches(page: str, res: dict) -> list[str]:
    """The generated blocks of ``page`` that differ from what ``res`` renders (or are missing)."""
    want, have = paper_page.render_blocks(res), paper_page.page_blocks(page)
    out = [f"{name}: missing from the page" for name in want if name not in have]
    for name in want:
        if name in have and have[name] != want[name]:
            diff = [f"  page: {a}\n  file: {b}" for a, b in zip(have[name].splitlines(), want[name].splitlines(), strict=False) if a != b]
            out.append(f"{name}: differs from results.json\n" + "\n".join(diff[:3] or ["  (line count differs)"]))
    return out


def stray_numbers(page: str) -> list[str]:
    """Decimal numbers written outside the generated blocks that no block holds (the arXiv id and the paper's
    section numbers aside)."""
    blocks = paper_page.page_blocks(page)
    inside = "\n".join(blocks.values())
    outside = re.sub(r"Sec\. [\d.]+\d", "", paper_page.BLOCK.sub("", page))
    return [n for n in NUMBER.findall(outside) if n not in paper_page.NOT_RESULTS and n.lstrip("+-−") not in inside]


def test_every_generated_table_equals_the_results_file(results):
    assert not block_mismatches(PAGE.read_text(), results), "\n".join(block_mismatches(PAGE.read_text(), results))
    # the script loads, and renders the page with the very functions checked here
    spec = importlib.util.spec_from_file_location("paper_reproduce", ROOT / "benchmarks" / "paper" / "reproduce.py")
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    sys.modules["paper_reproduce"] = script  # its dataclass looks its module up
    spec.loader.exec_module(script)
    assert script.render_blocks is paper_page.render_blocks and script.write_page is paper_page.write_page


def test_every_claim_has_its_section_and_verdict(results):
    page = PAGE.read_text()
    blocks = paper_page.page_blocks(page)
    verdicts = paper_numbers.VERDICTS
    for name in CLAIMS:
        assert name in blocks, f"no generated block for the claim {name!r}"
        found = re.findall(r"\*\*Verdict: ([a-z ]+)\.\*\*", blocks[name])
        assert found == [results["claims"][name]["verdict"]], (name, found)
        assert found[0] in verdicts
    sections = [s for s in re.split(r"\n(?=## )", page) if s.startswith("## Claim")]
    assert len(sections) == len(CLAIMS), [s.splitlines()[0] for s in sections]
    for s in sections:
        assert re.search(r"\*\*Verdict: (reproduced|reproduced in part|turned)\.\*\*", s), s.splitlines()[0]
        assert "**Why.**" in s, f"{s.splitlines()[0]}: the verdict's reason"


def test_numbers_outside_the_tables_come_from_them():
    page = PAGE.read_text()
    assert not stray_numbers(page), f"numbers in docs/paper.md that no generated block holds: {stray_numbers(page)}"


def test_the_check_fails_when_a_number_of_the_page_is_edited(results):
    page = PAGE.read_text()
    body = paper_page.page_blocks(page)["latency"]
    number = NUMBER.search(body.split("\n\n", 1)[1])  # the first number of the table of configurations
    assert number is not None
    edited_body = body.replace(number.group(), f"{number.group()}1", 1)
    edited = page.replace(body, edited_body, 1)
    assert edited != page
    assert block_mismatches(edited, results), "an edited number in a generated table went unnoticed"
    assert stray_numbers(page + "\nThe hybrid is 0.123456 times faster.\n") == ["0.123456"]


def test_the_results_file_says_how_it_was_made(results):
    assert results["mode"] in ("quick", "full")
    assert results["provenance"]["command"].startswith("python benchmarks/paper/reproduce.py")
    assert min(results["seeds"]["simulation"]) >= 9100  # held out: no other benchmark or test uses them
    assert results["paper"]["latency"]["full_ms"] == 1.954 and results["paper"]["hybrid"]["T"] == 1000
