"""The layout keeps its promises (docs/architecture.md): one frame loop, one
definition of each code and default, no import cycle, serving apart from the
torch side (hybridmpm.train), and no lazy import without its reason."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _sources(*dirs: str) -> list[Path]:
    return [p for d in dirs for p in (ROOT / d).rglob("*.py")]


def test_frames_are_advanced_only_inside_hybridmpm_sim():
    # MpmSolver.step_frame is called by the simulators; everything else goes through rollout
    sim = ROOT / "python" / "hybridmpm" / "sim"
    offenders = []
    for p in _sources("python", "benchmarks", "docs"):
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if "step_frame(" in line and sim not in p.parents and not line.lstrip().startswith(("def step_frame", "return self._core.step_frame")):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_codes_and_defaults_are_defined_once():
    # the numbers of hybridmpm.conventions are not restated as module constants elsewhere
    pattern = re.compile(
        r"^(WATER|SAND|KINEMATIC|GNS_(?:KINEMATIC|WATER|SAND|TYPE\w*)|MATERIAL_\w+|CONNECTIVITY_RADIUS|T_IN|T_CTR|R_C|DELTA|SPLITS|DT_FRAME|DEFAULT_RADIUS|DEFAULT_CONNECTIVITY_RADIUS|DEFAULT_N_GRID)\s*(:[^=]*)?=\s*[\d(\[{\"']"
    )
    offenders = []
    for p in _sources("python"):
        if p.name == "conventions.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if pattern.match(line):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_the_failure_check_defaults_are_the_conventions():
    # the failure checks' defaults (declared once, FailureChecks) are hybridmpm.conventions' values, not numbers of their own
    import dataclasses

    from hybridmpm import conventions
    from hybridmpm.sim import FailureChecks

    defaults = {f.name: f.default for f in dataclasses.fields(FailureChecks)}
    for name in ("ke_factor", "escape_cells", "degree_factor"):
        assert defaults[name] == getattr(conventions, f"FAILURE_{name.upper()}"), name
    for p in _sources("python/hybridmpm/sim"):
        assert not re.search(r"(ke_factor|escape_cells|degree_factor): float = \d", p.read_text()), p


def test_the_taichi_peer_is_not_in_the_package():
    assert not (ROOT / "python" / "hybridmpm" / "bench" / "taichi_peer.py").exists()
    for p in _sources("python"):
        assert "import taichi" not in p.read_text(), p


def test_one_name_per_concept():
    # the retired aliases stay retired: MATERIAL_WATER/MATERIAL_SAND, DOMAINS, conventions.GNS_KINEMATIC, GnsRuntime
    import importlib

    retired = {
        "hybridmpm": ("WATER", "SAND", "NeuralModel"),
        "hybridmpm.mpm": ("WATER", "SAND"),
        "hybridmpm.scenes": ("SCENES",),
        "hybridmpm.trajectory": ("KINEMATIC",),
        "hybridmpm.data": ("KINEMATIC",),
        "hybridmpm.data.gns": ("KINEMATIC",),
        "hybridmpm.neural": ("KINEMATIC", "NeuralModel"),
        "hybridmpm.neural.constants": ("KINEMATIC",),
        "hybridmpm.neural.runtime": ("NeuralModel",),
    }
    left = [f"{m}.{n}" for m, names in retired.items() for n in names if hasattr(importlib.import_module(m), n)]
    assert not left, left


def test_one_environment_variable_prefix_and_one_meaning_per_name():
    # every variable the package reads is HYBRIDMPM_*; the service's process budget is not the engine's allocation budget
    from dataclasses import fields

    from hybridmpm.limits import ENV_VAR
    from hybridmpm.service.config import ServiceConfig, env_name

    old_prefix = "HMPM" + "_"  # split so that this file is not an offender
    files = _sources("python", "benchmarks", "tests") + list((ROOT / "rust").rglob("*.rs")) + list((ROOT / "docs").glob("*.md"))
    files += [ROOT / "README.md", ROOT / "scripts" / "test.sh", ROOT / ".ci" / "run"]
    offenders = [f"{p.relative_to(ROOT)}" for p in files if old_prefix in p.read_text()]
    assert not offenders, offenders
    names = [env_name(f.name) for f in fields(ServiceConfig)]
    assert all(n.startswith("HYBRIDMPM_") for n in names) and len(set(names)) == len(names), names
    assert ENV_VAR not in names


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
    "experiments/learned_correction/features.py": "the learned correction's features, imported by go_no_go.py (which writes the results)",
    "experiments/learned_correction/forcing.py": "the correction's forcing callables, imported by go_no_go.py and train.py",
    "experiments/learned_correction/model.py": "the correction's numpy network, imported by go_no_go.py and train.py (its save is np.savez)",
    "experiments/learned_correction/teacher.py": "the correction's teacher (a coarse state on the scene's grid), imported by forcing.py",
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


# ------------------------------------------------------------------ the import graph
PACKAGE = ROOT / "python" / "hybridmpm"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _type_checking_only(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


class _Import(NamedTuple):
    target: str  # the module of the package that is imported
    line: int
    in_function: bool


def _imports(path: Path, modules: dict[str, Path], type_checking: bool = False) -> list[_Import]:
    """The package's own modules that ``path`` imports (``from a import b``
    names the module ``a.b`` when it is one, else ``a``); imports under
    ``if TYPE_CHECKING:`` are arrows only with ``type_checking`` (they never
    run, but a reader still needs the other module)."""
    found: list[_Import] = []

    def targets(node: ast.Import | ast.ImportFrom) -> list[str]:
        if isinstance(node, ast.Import):
            return [a.name for a in node.names]
        if node.level or not node.module:
            raise AssertionError(f"{path}:{node.lineno}: relative import (the package imports absolutely)")
        sub = [f"{node.module}.{a.name}" for a in node.names]
        return [s for s in sub if s in modules or s == "hybridmpm._core"] or [node.module]

    def walk(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if _type_checking_only(child) and not type_checking:
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for t in targets(child):
                    if t == "hybridmpm" or t.startswith("hybridmpm."):
                        found.append(_Import(t, child.lineno, in_function))
            walk(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(ast.parse(path.read_text()), False)
    return found


def _graph(type_checking: bool = False) -> dict[str, set[str]]:
    modules = _modules()
    return {name: {i.target for i in _imports(path, modules, type_checking) if i.target in modules and i.target != name} for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_package_has_no_import_cycle():
    # lazy imports count too: an import inside a function is still an arrow, so it cannot hide a circle; so do imports
    # for annotations only (under TYPE_CHECKING): the two modules still cannot be read, or moved, apart
    graph = _graph(type_checking=True)
    assert not _cycles(graph), _cycles(graph)


def _importers_of(prefix: str) -> dict[str, set[str]]:
    return {m: {t for t in ts if t == prefix or t.startswith(prefix + ".")} for m, ts in _graph().items()}


def _inside(module: str, *packages: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def test_only_the_make_side_imports_hybridmpm_train():
    # serving (neural/, control/, sim/, service/) runs exported files with numpy + onnxruntime; torch lives in train/
    offenders = {
        m: sorted(t) for m, t in _importers_of("hybridmpm.train").items() if t and not _inside(m, "hybridmpm.train", "hybridmpm.bench", "hybridmpm.cli")
    }
    assert not offenders, offenders


def test_the_simulators_import_neither_control_nor_bench_nor_the_generators():
    graph = _graph()
    offenders = {
        m: sorted(t for t in ts if _inside(t, "hybridmpm.control", "hybridmpm.bench", "hybridmpm.train", "hybridmpm.service"))
        for m, ts in graph.items()
        if _inside(m, "hybridmpm.sim")
    }
    assert not any(offenders.values()), offenders


def test_the_dataset_format_runs_no_simulation():
    # data/ is the GNS layout only; what makes datasets (and runs sim/) is hybridmpm.train.datasets
    graph = _graph()
    offenders = {
        m: sorted(ts)
        for m, ts in graph.items()
        if _inside(m, "hybridmpm.data") and any(_inside(t, "hybridmpm.sim", "hybridmpm.neural", "hybridmpm.scenes") for t in ts)
    }
    assert not offenders, offenders


# The service's lazy imports (file, imported module); the list only shrinks.
SERVICE_LAZY_IMPORTS = {
    ("service/config.py", "hybridmpm.limits"),
}


def test_in_function_imports_of_the_package_say_why():
    # an import of the package's own modules inside a function is there for import time (the CLI starts without
    # torch, the service without what a route alone needs), never to hide a circle: a comment on its line or the
    # line before its block of imports says so
    modules = _modules()
    offenders = []
    for path in modules.values():
        text = path.read_text()
        lines = text.splitlines()
        # the lines of every import statement (a block of imports shares the comment above its first)
        in_import = {n for node in ast.walk(ast.parse(text)) if isinstance(node, (ast.Import, ast.ImportFrom)) for n in range(node.lineno, node.end_lineno + 1)}
        rel = str(path.relative_to(PACKAGE))
        for imp in _imports(path, modules):
            if not imp.in_function or (rel, imp.target) in SERVICE_LAZY_IMPORTS or "#" in lines[imp.line - 1]:
                continue
            above = imp.line - 1
            while above in in_import and "#" not in lines[above - 1]:
                above -= 1
            if not (above >= 1 and "#" in lines[above - 1]):
                offenders.append(f"{rel}:{imp.line}: {lines[imp.line - 1].strip()}")
    assert not offenders, "\n".join(offenders)


# Stands in for an environment without the train extra: torch (and onnx) cannot be imported.
_NO_TORCH = """
import sys
from importlib.abc import MetaPathFinder

class NoTrainExtra(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("torch", "onnx", "onnxscript"):
            raise ImportError(f"{name} is not installed (the train extra)")
        return None

sys.meta_path.insert(0, NoTrainExtra())
import hybridmpm, hybridmpm.sim, hybridmpm.neural, hybridmpm.control, hybridmpm.service.app
loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "onnx", "onnxscript") or m.startswith("hybridmpm.train"))
assert not loaded, loaded
print("ok")
"""


def test_serving_imports_without_torch():
    out = subprocess.run([sys.executable, "-c", _NO_TORCH], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_the_connectivity_radius_value_is_written_once():
    # R = 0.015 m lives in Rust (the neighbors crate), read once by hybridmpm.conventions; defaults elsewhere name CONNECTIVITY_RADIUS
    pattern = re.compile(r"(?<![\d.])0\.015(?!\d)")
    offenders = []
    for p in _sources("python"):
        if p.name == "conventions.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            code = line.split("#", 1)[0]
            if pattern.search(code) and '"""' not in line and not line.lstrip().startswith(("``", "-", "*")):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_routes_read_session_facts_not_the_simulator():
    # a route reads a session's plain facts (service/facts.py), the same on both backends; reaching into `s.sim`
    # is what once needed a stand-in simulator on the Ray front end, and a session's core is its backend's
    offenders = []
    for p in sorted((PACKAGE / "service" / "routes").glob("*.py")):
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if re.search(r"(?<!hybridmpm)(?<!service)\.(sim|core)\b", line):  # s.sim, s.core; not the modules hybridmpm.sim, hybridmpm.service.core
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


# What a session does with its simulator, called only by its core (service/core.py) — the play step, a rollout,
# a save's snapshot, a rebuild from the store, the control episode, the pacing and the recording — so that the
# local backend and the Ray actor run one session core instead of two copies of it.
_SESSION_WORK = {"rollout", "advance", "record_state", "make_simulator", "rebuild", "run_episode", "Pacer", "Recording", "control_episode"}
# where those names are defined (each defines one and calls none of the others on a session)
_SESSION_WORK_HOMES = {"core.py", "store.py", "episode.py", "budget.py"}


def test_one_session_core_does_a_sessions_work():
    offenders = []
    for p in sorted((PACKAGE / "service").rglob("*.py")):
        if p.parent.name == "service" and p.name in _SESSION_WORK_HOMES:
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
                seam = isinstance(f, ast.Attribute) and ast.unparse(f.value).split(".")[-1] in ("core", "manager")  # core.rollout, manager.rollout
                if name in _SESSION_WORK and not seam:
                    offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: {name}(...)")
    assert not offenders, "\n".join(offenders)


def test_the_ray_backend_lives_in_its_folder():
    # only service/ray_backend/ imports ray; the local backend and the routes never do
    offenders = []
    for p in sorted((PACKAGE / "service").rglob("*.py")):
        if p.parent.name == "ray_backend":
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            offenders += [f"{p.relative_to(ROOT)}:{node.lineno}: import {n}" for n in names if n.split(".")[0] == "ray"]
    assert not offenders, "\n".join(offenders)


def test_the_controls_route_keeps_admission_and_the_http_shape_only():
    # a control's budgets, watch, saves, events and kept control live in service/controls.py
    tree = ast.parse((PACKAGE / "service" / "routes" / "controls.py").read_text())
    (route,) = [n for n in tree.body if isinstance(n, ast.AsyncFunctionDef) and n.name == "control"]
    assert route.end_lineno - route.lineno + 1 <= 50


def test_no_python_file_of_the_package_is_over_700_lines():
    big = {str(p.relative_to(ROOT)): n for p in PACKAGE.rglob("*.py") if (n := len(p.read_text().splitlines())) > 700}
    assert not big, big


def test_no_rust_source_file_is_over_700_lines():
    # test modules and integration tests included: a concept too big for a file becomes a folder
    sources = list((ROOT / "rust").rglob("*.rs"))
    assert len(sources) > 50, "the Rust sources were not found"
    big = {str(p.relative_to(ROOT)): n for p in sources if (n := len(p.read_text().splitlines())) > 700}
    assert not big, big


def test_no_docs_page_is_over_500_lines():
    # a page is a reference a user acts on; dated rounds of experiments go to docs/history/
    pages = list((ROOT / "docs").glob("*.md"))
    assert len(pages) > 10, "the docs pages were not found"
    big = {str(p.relative_to(ROOT)): n for p in pages if (n := len(p.read_text().splitlines())) > 500}
    assert not big, big


def test_no_class_stands_in_for_a_simulator_in_the_service():
    # the service holds real simulators (local sessions, actors) or none (a Ray front end's session has sim=None)
    offenders = []
    for p in sorted((PACKAGE / "service").rglob("*.py")):
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and ("Sim" in node.name and "View" in node.name or node.name.endswith("Simulator")):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: class {node.name}")
    assert not offenders, "\n".join(offenders)


# The one private module that crosses modules: the compiled extension, whose public face is its typed wrappers
# (hybridmpm.mpm, hybridmpm.graph, ...); its name is the extension's, not a private name of another module.
_EXTENSION = "hybridmpm._core"


def _bench_modules() -> set[str]:
    """The names under which benchmark files import each other: the top-level
    scripts by stem and the experiments' modules by dotted path (their scripts
    put ``benchmarks/`` on ``sys.path``)."""
    bench = ROOT / "benchmarks"
    names = {p.stem for p in bench.glob("*.py")}
    for p in (bench / "experiments").rglob("*.py"):
        parts = list(p.relative_to(bench).with_suffix("").parts)
        names.add(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def _private(dotted: str) -> bool:
    return dotted != _EXTENSION and any(part.startswith("_") and not part.startswith("__") for part in dotted.split("."))


def _private_imports(path: Path, modules: dict[str, Path], local: set[str]) -> list[str]:
    """What ``path`` imports of another module's private names: ``from a import
    _b``, ``import a._b`` or ``a._b`` through an imported module, where ``a`` is
    a module of the package or one of ``local`` (in a function or not)."""

    def ours(module: str) -> bool:
        return module == "hybridmpm" or module.startswith("hybridmpm.") or module.split(".")[0] in {m.split(".")[0] for m in local}

    found = []
    tree = ast.parse(path.read_text())
    aliases: dict[str, str] = {}  # local name -> module of ours it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and ours(node.module):
            for a in node.names:
                full = f"{node.module}.{a.name}"
                if _private(full):
                    found.append(f"{node.lineno}: from {node.module} import {a.name}")
                if full in modules or full == _EXTENSION or full in local:
                    aliases[a.asname or a.name] = full
        elif isinstance(node, ast.Import):
            for a in node.names:
                if ours(a.name):
                    if _private(a.name):
                        found.append(f"{node.lineno}: import {a.name}")
                    aliases[a.asname or a.name] = a.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = ast.unparse(node.value)
            if base in aliases and _private(f"{aliases[base]}.{node.attr}"):
                found.append(f"{node.lineno}: {base}.{node.attr}")
    return found


def test_no_private_name_is_imported_across_modules():
    """A name with a leading underscore is its module's own: no module of the
    package imports one from another (``from a import _b``, ``import a._b``,
    or ``a._b`` through an imported module), in a function or not, and no
    benchmark file imports one from the package or from another benchmark
    file. What a neighbour needs is public API of the module that owns it,
    documented there (the surfaces: ``render/surface_field.py`` serves
    ``render/surface.py`` and ``render/usd.py``). There is no exception for
    modules of one package: a pair that shares its privates is one concept
    cut in two. The one private module imported across modules is the
    compiled extension ``hybridmpm._core``."""
    modules, local = _modules(), _bench_modules()
    offenders = [f"{name}:{o}" for name, path in sorted(modules.items()) for o in _private_imports(path, modules, set())]
    for path in sorted((ROOT / "benchmarks").rglob("*.py")):
        offenders += [f"{path.relative_to(ROOT)}:{o}" for o in _private_imports(path, modules, local)]
    assert not offenders, "\n".join(offenders)


#: Underscore names that are public API by their owners' convention (namedtuple's methods and fields, ``os._exit``).
_PUBLIC_UNDERSCORE = {"_replace", "_asdict", "_fields", "_field_defaults", "_make", "_exit"}


def _own_private_names(tree: ast.AST) -> set[str]:
    """The private names a module defines itself: functions, classes and
    variables at any level (methods and class attributes included) and the
    attributes it assigns (``x._a = ...``, ``self._a: T = ...``)."""
    own: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            own.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            own.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            own.add(node.attr)
    return {n for n in own if n.startswith("_")}


def _private_attribute_reaches(path: Path) -> list[str]:
    """Where ``path`` reads or calls ``obj._name`` (``obj`` not ``self`` or
    ``cls``) for a private ``_name`` that it does not define itself: another
    module's object reached through its privates."""
    tree = ast.parse(path.read_text())
    own = _own_private_names(tree) | _PUBLIC_UNDERSCORE
    found = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and node.attr not in own
            and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
        ):
            found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def test_no_object_is_reached_through_another_modules_privates():
    # obj._name where _name belongs to a class of another module (sim._prepare_restore, solver._get, a NeuralSimulator's
    # _failure): the owner makes it public and documents it (MpmSimulator.prepare_restore, MpmSolver.field/set_field,
    # NeuralSimulator.failure_of). A module may reach its own classes' privates on other instances (a classmethod's new
    # object, a manager's lock); a private name it defines itself counts as its own. Benchmarks included.
    files = [*PACKAGE.rglob("*.py"), *(ROOT / "benchmarks").rglob("*.py")]
    offenders = [f"{p.relative_to(ROOT)}:{o}" for p in sorted(files) for o in _private_attribute_reaches(p)]
    assert not offenders, "\n".join(offenders)


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


def test_the_training_families_stand_on_the_one_scaffold():
    # the GNS, the grid model and the controller start with start_run and train through TrainingLoop; none calls
    # torch.save itself (checkpoints and best weights go through the scaffold's atomic save_torch)
    trainers = {"gns/train.py": "_train", "grid/train.py": "_train_grid", "control/train.py": "_train_control"}
    for rel, fn in trainers.items():
        tree = ast.parse((PACKAGE / "train" / rel).read_text())
        (node,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == fn]
        called = {ast.unparse(c.func).split(".")[-1] for c in ast.walk(node) if isinstance(c, ast.Call)}
        assert {"TrainingLoop", "start_run"} <= called, (rel, sorted(called))
        saves = [f"{rel}:{c.lineno}" for c in ast.walk(tree) if isinstance(c, ast.Call) and ast.unparse(c.func) == "torch.save"]
        assert not saves, saves
    assert not (PACKAGE / "train" / "grid_train.py").exists() and (PACKAGE / "train" / "grid" / "__init__.py").exists()


# ------------------------------------------------------------------ the session backends
SERVICE = PACKAGE / "service"


def _service_classes() -> dict[str, tuple[Path, ast.ClassDef]]:
    return {n.name: (p, n) for p in sorted(SERVICE.rglob("*.py")) for n in ast.walk(ast.parse(p.read_text())) if isinstance(n, ast.ClassDef)}


def test_no_session_manager_or_handle_subclasses_another():
    # the local and the Ray backends stand side by side on one protocol (service/backend.py), sharing helpers, not a base class
    classes = _service_classes()
    offenders = []
    for name, (p, node) in classes.items():
        if not name.endswith(("Manager", "Session")):
            continue
        for base in node.bases:
            b = ast.unparse(base).split("[")[0].split(".")[-1]
            if b in classes and b.endswith(("Manager", "Session")):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: class {name}({ast.unparse(base)})")
    assert not offenders, "\n".join(offenders)


def _methods(node: ast.ClassDef) -> dict[str, list[str]]:
    """The methods defined in a class body (not inherited), with their parameter names."""
    return {
        f.name: [a.arg for a in (*f.args.posonlyargs, *f.args.args, *f.args.kwonlyargs)]
        for f in node.body
        if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
    }


def test_both_backends_implement_the_session_backend_protocol_themselves():
    # every method of SessionBackend (what the routes call) is written in each backend's own class, with the protocol's
    # parameter names (FastAPI's dependencies and the control runner call them by keyword too); the protocol's attributes
    # are set by each. A backend that inherited its methods from the other would fail here
    classes = _service_classes()
    protocol = _methods(classes["SessionBackend"][1])
    attributes = {ast.unparse(n.target) for n in classes["SessionBackend"][1].body if isinstance(n, ast.AnnAssign)}
    assert {"find", "create", "close", "info", "rollout", "run_control", "attach", "compute"} <= set(protocol)
    for name in ("SessionManager", "RaySessionManager"):
        path, node = classes[name]
        have = _methods(node)
        missing = sorted(m for m in protocol if m not in have)
        differ = sorted(m for m in protocol if m in have and have[m][: len(protocol[m])] != protocol[m])
        assert not missing and not differ, (name, missing, differ)
        text = ast.unparse(node)
        unset = sorted(a for a in attributes if f"self.{a} =" not in text and not re.search(rf"^\s*{a}\s*=", text, re.M))
        assert not unset, (name, unset)


def test_the_routes_type_their_backend_with_the_protocol():
    # the routes, their dependencies and the control runner name SessionBackend and Session (service/backend.py), never a
    # backend's class: what they call of a backend is the protocol, the same on either
    files = [*sorted((SERVICE / "routes").glob("*.py")), SERVICE / "deps.py", SERVICE / "controls.py"]
    concrete = {"SessionManager", "RaySessionManager", "LocalSession", "RaySession"}
    offenders = []
    annotated = 0
    for p in files:
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module in ("hybridmpm.service.sessions", "hybridmpm.service.ray_backend.manager"):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: from {node.module} import ...")
            if isinstance(node, ast.Name) and node.id in concrete:
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: {node.id}")
            if isinstance(node, ast.arg) and node.arg == "manager" or isinstance(node, ast.AnnAssign) and ast.unparse(node.target) == "manager":
                ann = node.annotation
                annotated += 1
                if ann is None or ast.unparse(ann) not in ("ManagerDep", "SessionBackend[Any]"):
                    offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: manager: {ann and ast.unparse(ann)}")
    deps = (SERVICE / "deps.py").read_text()
    assert "ManagerDep = Annotated[SessionBackend[Any], Depends(get_manager)]" in deps
    assert "SessionDep = Annotated[Session, Depends(session_or_404)]" in deps and "from hybridmpm.service.backend import Session, SessionBackend" in deps
    assert annotated >= 10, annotated
    assert not offenders, "\n".join(offenders)


def _calls(path: Path, name: str) -> list[int]:
    """Lines of ``path`` that call ``name`` (a plain name or an attribute's last part)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            if (f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else "") == name:
                found.append(node.lineno)
    return found


def test_each_rule_of_a_session_is_written_once():
    # a frame's bytes for its viewers: frames.frame_message (encode_frame, the wire format, is called only there)
    enc = {str(p.relative_to(SERVICE)): _calls(p, "encode_frame") for p in SERVICE.rglob("*.py")}
    assert {k: v for k, v in enc.items() if v} == {"frames.py": enc["frames.py"]} and len(enc["frames.py"]) == 1, enc
    # the record-expiry rule: StoredSession.expired in the store, nowhere else compared by hand
    by_hand = [
        f"{p.relative_to(ROOT)}:{i}"
        for p in SERVICE.rglob("*.py")
        if p.name != "store.py"
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if "last_used_at" in line and ">" in line
    ]
    assert not by_hand, by_hand
    # kill-the-actor-and-release-the-registry: once in the front end (RaySessionManager._end)
    manager = SERVICE / "ray_backend" / "manager.py"
    assert len(_calls(manager, "kill")) == 1 and len([n for n in _calls(manager, "remote") if "release.remote" in manager.read_text().splitlines()[n - 1]]) == 1
    # a real-time session's share: capacity.share_of, called by the local rule (realtime_share) and a Ray actor's reporter
    shares = {str(p.relative_to(SERVICE)): n for p in SERVICE.rglob("*.py") if (n := len(_calls(p, "share_of")))}
    assert shares == {"capacity.py": 1, "ray_backend/shares.py": 1}, shares
    assert "REALTIME_SHARE * compute_threads / threads" in (SERVICE / "capacity.py").read_text()
    # the save policy around a control: the core's (SessionCore.control); the control runner and the actor save nothing themselves
    runner = ast.parse((SERVICE / "controls.py").read_text())
    assert not [c.lineno for c in ast.walk(runner) if isinstance(c, ast.Call) and ast.unparse(c.func).startswith(("manager.save", "s.save"))]
    actor = ast.parse((SERVICE / "ray_backend" / "actor.py").read_text())
    (run_control,) = [n for n in ast.walk(actor) if isinstance(n, ast.FunctionDef) and n.name == "run_control"]
    assert not [c for c in ast.walk(run_control) if isinstance(c, ast.Call) and ast.unparse(c.func).endswith(".save")]


# ------------------------------------------------------------------ the page
STATIC = SERVICE / "static"


def test_no_javascript_file_of_the_page_is_over_700_lines():
    # the page's ES modules keep the cap of the Python and Rust sources: a concept too big for a file becomes modules
    scripts = list(STATIC.rglob("*.js"))
    assert len(scripts) > 5, "the page's scripts were not found"
    big = {str(p.relative_to(ROOT)): n for p in scripts if (n := len(p.read_text().splitlines())) > 700}
    assert not big, big


def test_the_page_takes_the_particle_type_codes_from_the_conventions():
    # static/*.js write no GNS particle-type code, neither as a constant (WATER = 5) nor compared by hand (types[i] === 3,
    # GLSL's t == 5.0): they import the names from /codes.js, which the service makes from hybridmpm.conventions
    from hybridmpm import conventions

    codes = {
        "WALL": conventions.GNS_KINEMATIC,
        "WATER": conventions.GNS_WATER,
        "SAND": conventions.GNS_SAND,
        "MUD": conventions.GNS_GOOP,
        "JELLY": conventions.GNS_ELASTIC,
        "SNOW": conventions.GNS_SNOW,
    }
    numbers = "|".join(str(c) for c in sorted(set(codes.values())))
    by_hand = re.compile(
        rf"\b(WATER|SAND|WALL|KINEMATIC|MUD|GOOP|JELLY|ELASTIC|SNOW)\s*[:=]\s*\d|(?<![.\w])(t|v_type|types\[\w+\]|particle_type\[\w+\])\s*[!=]==?\s*({numbers})(\.0)?\b"
    )
    offenders, imported = [], {}
    for p in sorted(STATIC.rglob("*.js")):
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if by_hand.search(line.split("//", 1)[0]):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
            if m := re.match(r'import \{([^}]*)\} from "/codes\.js";', line):
                imported[p.name] = {n.strip() for n in m.group(1).split(",")}
    assert not offenders, "\n".join(offenders)
    assert {"render.js", "shaders.js", "cells.js", "colors.js", "app.js"} <= set(imported), imported

    pytest.importorskip("fastapi")
    pytest.importorskip("httpx")
    from fastapi.testclient import TestClient

    from hybridmpm.service import ServiceConfig, create_app

    with TestClient(create_app(ServiceConfig())) as client:
        r = client.get("/codes.js")
        assert client.post("/codes.js").status_code == 405
    # a module script needs a JavaScript type
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/javascript"), (r.status_code, r.headers)
    served = {name: int(code) for name, code in re.findall(r"^export const (\w+) = (\d+);$", r.text, re.M)}
    assert served == codes, r.text
    assert all(names <= set(served) for names in imported.values()), imported
