"""The layout keeps its promises (docs/architecture.md): one frame loop, one
definition of each code and default, no import cycle, serving apart from the
torch side (hybridmpm.train), and no lazy import without its reason. The
benchmarks' harness, the service's session backends and page, and the limits on
a file's length have files of their own: tests/test_architecture_*.py."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

from _arch import PACKAGE, ROOT


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


# ------------------------------------------------------------------ the import graph


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


# The one private module that crosses modules: the compiled extension, whose public face is its typed wrappers
# (hybridmpm.mpm, hybridmpm.graph, ...); its name is the extension's, not a private name of another module.
_EXTENSION = "hybridmpm._core"


def _bench_modules() -> set[str]:
    """The names under which benchmark files import each other: the top-level
    scripts and the paper's reproduction (which puts its folder on ``sys.path``)
    by stem, and the experiments' modules by dotted path (their scripts put
    ``benchmarks/`` on ``sys.path``)."""
    bench = ROOT / "benchmarks"
    names = {p.stem for p in [*bench.glob("*.py"), *(bench / "paper").glob("*.py")]}
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
