"""The benchmark harness (hybridmpm.bench.harness): repeats go round the
configurations, results carry their provenance, and a failed write leaves the
previous result whole."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from hybridmpm.bench import harness


def test_round_robin_takes_every_configuration_before_repeating_one():
    calls: list[str] = []
    res = harness.round_robin(["a", "b", "c"], 3, lambda c: calls.append(c) or f"{c}{len(calls)}")
    assert calls == ["a", "b", "c"] * 3
    assert res == [["a1", "a4", "a7"], ["b2", "b5", "b8"], ["c3", "c6", "c9"]]
    with pytest.raises(ValueError, match="repeats"):
        harness.round_robin(["a"], 0, str)


def test_provenance_names_the_commit_the_command_and_the_load(tmp_path):
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=harness.REPO_ROOT, capture_output=True, text=True).stdout.strip()
    prov = harness.provenance([str(harness.REPO_ROOT / "benchmarks" / "x.py"), "--out", "a b"])
    assert prov["commit"].removesuffix("-dirty") == head
    assert prov["command"] == "python benchmarks/x.py --out 'a b'"
    assert harness.command(["/somewhere/.venv/bin/hybridmpm", "bench", "water2d"]) == "hybridmpm bench water2d"  # an installed command
    assert prov["cores"] == os.cpu_count()
    assert len(prov["load_before"]) == len(prov["load_after"]) == 3
    assert prov["load_after"][0] == pytest.approx(os.getloadavg()[0], abs=0.5)
    assert prov["started"] <= prov["date"]


def test_write_results_puts_provenance_in_the_json_and_a_header_under_the_title(tmp_path):
    paths = harness.write_results(tmp_path / "r", "grids", doc={"rows": [1, 2]}, markdown=["# Title\n\ntext", "| a |\n|---|\n| 1 |"], argv=["bench.py", "-q"])
    doc = json.loads(paths["json"].read_text())
    assert list(doc) == ["provenance", "rows"] and doc["rows"] == [1, 2]
    assert doc["provenance"]["command"] == "python bench.py -q"
    lines = paths["md"].read_text().splitlines()
    assert lines[0] == "# Title" and lines[2] == "Command: `python bench.py -q`  "
    assert lines[3].startswith("Machine: ") and lines[4].startswith("Run: ")
    assert lines[6:] == ["text", "", "| a |", "|---|", "| 1 |"]
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["grids.json", "grids.md"]  # no temporary file left
    with pytest.raises(ValueError, match="provenance"):
        harness.write_results(tmp_path, "x", doc={"provenance": 1})


def test_an_appended_section_keeps_what_the_file_held(tmp_path):
    harness.write_results(tmp_path, "service", markdown="\n## First\n\none", append=True)
    harness.write_results(tmp_path, "service", markdown="\n## Second\n\ntwo", append=True)
    text = (tmp_path / "service.md").read_text()
    assert text.index("## First") < text.index("one") < text.index("## Second") < text.index("two")
    assert text.count("Command: ") == 2


def test_a_failed_write_leaves_the_previous_result_whole(tmp_path):
    harness.write_results(tmp_path, "r", doc={"v": 1})
    before = (tmp_path / "r.json").read_text()
    with pytest.raises(TypeError, match="object"):
        harness.write_results(tmp_path, "r", doc={"v": object()})
    assert (tmp_path / "r.json").read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]


def test_read_results_takes_old_bare_lists_as_rows(tmp_path):
    (tmp_path / "old.json").write_text("[1, 2]")
    assert harness.read_results(tmp_path / "old.json") == {"rows": [1, 2]}
    harness.write_results(tmp_path, "new", doc={"rows": [3]})
    assert harness.read_results(tmp_path / "new.json")["rows"] == [3]


def test_table_lines():
    assert harness.table(["a", "b"], [(1, 2.5)], align="lr") == ["| a | b |", "|---|---:|", "| 1 | 2.5 |"]
