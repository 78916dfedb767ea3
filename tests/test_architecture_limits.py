"""The limits on a file's length (docs/architecture.md): no Python, Rust or
JavaScript file that git tracks is over 700 lines, wherever it lives (the
package, the crates, the page, the tests, the benchmarks); no docs page is over
500 lines, no function of the training package over 120."""

from __future__ import annotations

import ast
import subprocess
from pathlib import Path

from _arch import PACKAGE, ROOT, STATIC

#: The longest a Python, Rust or JavaScript file may be, in lines: a concept too big for a file becomes a folder (or
#: modules), a test file splits by subject, a script's coherent group of functions moves to a module beside it.
SOURCE_LINES = 700


def _over(paths: list[Path], limit: int) -> dict[str, int]:
    """The files of ``paths`` over ``limit`` lines, longest first: {path in the repository: lines}."""
    lengths = {str(p.relative_to(ROOT)): len(p.read_text().splitlines()) for p in paths}
    return dict(sorted(((k, n) for k, n in lengths.items() if n > limit), key=lambda kv: (-kv[1], kv[0])))


def _tracked(*patterns: str) -> list[Path]:
    """The files git tracks that match ``patterns`` (at any depth) and are in the working tree."""
    out = subprocess.run(["git", "ls-files", "-z", "--", *patterns], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, f"git ls-files failed (the check reads the files git tracks): {out.stderr.strip()}"
    return [ROOT / f for f in out.stdout.split("\0") if f and (ROOT / f).is_file()]


def test_no_tracked_source_file_is_over_700_lines():
    # every Python, Rust and JavaScript file of the repository: the package, the crates, the page, tests/, benchmarks/,
    # scripts/ and docs/' figure scripts alike
    files = _tracked("*.py", "*.rs", "*.js")
    assert len(files) > 400 and {p.suffix for p in files} == {".py", ".rs", ".js"}, "the tracked sources were not found"
    big = _over(files, SOURCE_LINES)
    assert not big, f"over {SOURCE_LINES} lines: {big}"


def test_no_python_file_of_the_package_is_over_700_lines():
    big = _over(list(PACKAGE.rglob("*.py")), SOURCE_LINES)
    assert not big, big


def test_no_rust_source_file_is_over_700_lines():
    # test modules and integration tests included: a concept too big for a file becomes a folder
    sources = list((ROOT / "rust").rglob("*.rs"))
    assert len(sources) > 50, "the Rust sources were not found"
    big = _over(sources, SOURCE_LINES)
    assert not big, big


def test_no_javascript_file_of_the_page_is_over_700_lines():
    # the page's ES modules keep the cap of the Python and Rust sources: a concept too big for a file becomes modules
    scripts = list(STATIC.rglob("*.js"))
    assert len(scripts) > 5, "the page's scripts were not found"
    big = _over(scripts, SOURCE_LINES)
    assert not big, big


def test_no_docs_page_is_over_500_lines():
    # a page is a reference a user acts on; dated rounds of experiments go to docs/history/
    pages = list((ROOT / "docs").glob("*.md"))
    assert len(pages) > 10, "the docs pages were not found"
    big = _over(pages, 500)
    assert not big, big


#: The longest function the training package may hold, in lines (its def line to its last, nested functions included).
TRAIN_FUNCTION_LINES = 120


def test_no_function_in_the_training_package_is_over_120_lines():
    # a family's trainer is its parts (data, step, evaluation, export) on the one scaffold (hybridmpm.train.scaffold)
    offenders = []
    for p in sorted((PACKAGE / "train").rglob("*.py")):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and (n := node.end_lineno - node.lineno + 1) > TRAIN_FUNCTION_LINES:
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: {node.name} is {n} lines")
    assert not offenders, "\n".join(offenders)
