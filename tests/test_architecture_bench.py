"""The benchmarks keep the architecture's rules (docs/architecture.md): every
script is listed in benchmarks/README.md and writes through the one harness
(hybridmpm.bench.harness), which alone describes the machine."""

from __future__ import annotations

import ast
from pathlib import Path

from _arch import PACKAGE, ROOT


def test_every_benchmark_script_is_listed_in_the_benchmarks_readme():
    # benchmarks/NAME as `NAME`, the release scripts benchmarks/release/NAME as `release/NAME`
    bench = ROOT / "benchmarks"
    readme = (bench / "README.md").read_text()
    files = [*bench.iterdir(), *(bench / "release").iterdir()]
    scripts = sorted(str(p.relative_to(bench)) for p in files if p.suffix in (".py", ".sh") and not p.name.startswith("_"))
    missing = [s for s in scripts if f"`{s}`" not in readme]
    assert not missing, f"benchmarks/README.md does not list {missing}"


# ------------------------------------------------------------------ the benchmark harness
#: Scripts that write no file (they print, and their exit status is the result): they need not import the harness.
BENCH_WRITES_NOTHING = {"compare_errors.py": "prints the comparison; its exit status says whether the errors agree"}
#: (script, function) that may write a file or name the machine itself, and why.
BENCH_OWN_WRITES = {
    ("blender_import.py", "inside"): "runs in Blender's own Python, which has no hybridmpm: it hands its result file to the outer "
    "process (which writes the summary through the harness) and reports Blender's Python version",
}
#: Scripts not on the harness yet, and why (each must still need its entry: a converted script leaves the list).
BENCH_NOT_YET: dict[str, str] = {}
#: Files under benchmarks/ that are not runnable scripts (no ``__main__`` guard), so need not import the harness themselves,
#: and why; they still write nothing past it. Packages' ``__init__.py`` files (markers, no code) need no entry.
BENCH_MODULES = {
    "blender_files.py": "the exported files' figures (PLY, OBJ, run.usd through pxr), imported by blender_import.py (which writes the summary)",
    "experiments/learned_correction/features.py": "the learned correction's features, imported by go_no_go.py (which writes the results)",
    "experiments/learned_correction/forcing.py": "the correction's forcing callables, imported by go_no_go.py and train.py",
    "experiments/learned_correction/model.py": "the correction's numpy network, imported by go_no_go.py and train.py (its save is np.savez)",
    "experiments/learned_correction/teacher.py": "the correction's teacher (a coarse state on the scene's grid), imported by forcing.py",
    "paper/paper_numbers.py": "the paper's numbers, scenes and methods, imported by reproduce.py and paper_page.py",
    "paper/paper_page.py": "docs/paper.md's tables and figures from the results file, imported by reproduce.py (it writes through the harness)",
}
#: Calls that write a file, by the called attribute's name.
_WRITING_METHODS = {"write_text", "write_bytes", "savefig"}


def _bench_scripts() -> list[Path]:
    """Every Python file under benchmarks/, at any depth (the release scripts, the experiments, the paper's reproduction)."""
    return sorted((ROOT / "benchmarks").rglob("*.py"))


def _runnable(text: str) -> bool:
    return any(isinstance(n, ast.If) and ast.unparse(n.test).replace("'", '"') == '__name__ == "__main__"' for n in ast.parse(text).body)


def _bench_offences(text: str) -> list[str]:
    """What in a benchmark script's source writes a file or describes the
    machine other than through hybridmpm.bench.harness: ``.write_text``,
    ``.write_bytes``, ``.savefig``, ``json.dump`` and ``open``/``Path.open``
    with a mode that writes ("w", "a", "x", "+"); importing ``platform`` or
    ``hybridmpm.bench.env``, ``os.getloadavg``, ``/proc/cpuinfo`` and
    ``git rev-parse``. Each as ``function:line: what`` (``<module>`` at the
    top level)."""
    found: list[str] = []

    def mode_writes(node: ast.Call, index: int) -> bool:
        mode = node.args[index] if len(node.args) > index else next((k.value for k in node.keywords if k.arg == "mode"), None)
        return isinstance(mode, ast.Constant) and isinstance(mode.value, str) and any(c in mode.value for c in "wax+")

    def visit(node: ast.AST, func: str) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            func = node.name
        what = None
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Attribute) and f.attr in _WRITING_METHODS:
                what = f".{f.attr}()"
            elif isinstance(f, ast.Attribute) and f.attr == "dump" and isinstance(f.value, ast.Name) and f.value.id == "json":
                what = "json.dump()"
            elif isinstance(f, ast.Name) and f.id == "open" and mode_writes(node, 1):
                what = "open() for writing"
            elif isinstance(f, ast.Attribute) and f.attr == "open" and not (isinstance(f.value, ast.Name) and f.value.id == "os") and mode_writes(node, 0):
                what = ".open() for writing"
            elif isinstance(f, ast.Attribute) and f.attr == "getloadavg":
                what = "os.getloadavg()"
        elif isinstance(node, ast.Import) and any(a.name == "platform" for a in node.names):
            what = "import platform"
        elif isinstance(node, ast.ImportFrom) and node.module in ("platform", "hybridmpm.bench.env"):
            what = f"from {node.module} import"
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and ("/proc/cpuinfo" in node.value or "rev-parse" in node.value):
            what = repr(node.value)
        if what:
            found.append(f"{func}:{node.lineno}: {what}")
        for child in ast.iter_child_nodes(node):
            visit(child, func)

    visit(ast.parse(text), "<module>")
    return found


def _imports_the_harness(text: str) -> bool:
    return any(
        (isinstance(n, ast.ImportFrom) and n.module == "hybridmpm.bench.harness")
        or (isinstance(n, ast.ImportFrom) and n.module == "hybridmpm.bench" and any(a.name == "harness" for a in n.names))
        or (isinstance(n, ast.Import) and any(a.name == "hybridmpm.bench.harness" for a in n.names))
        for n in ast.walk(ast.parse(text))
    )


def test_every_benchmark_script_writes_through_the_one_harness():
    # The rule: every Python script under benchmarks/ (any depth) imports hybridmpm.bench.harness (unless it writes
    # no file: BENCH_WRITES_NOTHING), and none writes a file itself (.write_text, .write_bytes, .savefig, json.dump, open for
    # writing) or describes the machine itself (platform, hybridmpm.bench.env, os.getloadavg, /proc/cpuinfo, git rev-parse):
    # results go through write_results (their JSON with provenance, their Markdown under the command/machine/load header),
    # other files through write_file/write_json/save_figure, the load through load_average. Exceptions are named with their
    # reason (BENCH_OWN_WRITES by function, BENCH_NOT_YET by script).
    # Files that are not runnable scripts (BENCH_MODULES, __init__.py) need not import it but write nothing themselves either.
    offenders, stale = [], []
    for p in _bench_scripts():
        rel = p.relative_to(ROOT / "benchmarks").as_posix()
        text = p.read_text()
        found = [o for o in _bench_offences(text) if (rel, o.split(":", 1)[0]) not in BENCH_OWN_WRITES]
        module = p.name == "__init__.py" or rel in BENCH_MODULES
        if module and _runnable(text):
            found.append("runs as a script (a __main__ guard): it is no module, take it out of BENCH_MODULES")
        if not _imports_the_harness(text) and rel not in BENCH_WRITES_NOTHING and not module:
            found.append("does not import hybridmpm.bench.harness")
        if rel in BENCH_NOT_YET:
            stale += [] if found else [rel]
            continue
        offenders += [f"benchmarks/{rel}: {o}" for o in found]
    assert not offenders, "\n".join(offenders)
    assert not stale, f"on the harness now: remove {stale} from BENCH_NOT_YET"
    gone = [m for m in BENCH_MODULES if not (ROOT / "benchmarks" / m).is_file()]
    assert not gone, f"BENCH_MODULES names files that are gone: {gone}"
    used = {(s, f) for s, f in BENCH_OWN_WRITES if any(o.startswith(f"{f}:") for o in _bench_offences((ROOT / "benchmarks" / s).read_text()))}
    assert used == set(BENCH_OWN_WRITES), f"BENCH_OWN_WRITES entries no longer needed: {set(BENCH_OWN_WRITES) - used}"


def test_the_bench_package_describes_the_machine_through_the_harness():
    # hybridmpm bench (bench/run.py) records the same provenance as the scripts: only the harness reads bench/env.py's
    # machine description (environment()), so there is one
    offenders = []
    for p in sorted((PACKAGE / "bench").glob("*.py")):
        if p.name in ("harness.py", "env.py"):
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "hybridmpm.bench.env" and any(a.name == "environment" for a in node.names):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, offenders
    assert "from hybridmpm.bench.harness import provenance" in (PACKAGE / "bench" / "run.py").read_text()
