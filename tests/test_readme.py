"""The README says what runs.

* Its defaults table is the code's defaults: each row's simulator is the
  scene's configuration in ``python/hybridmpm/models/defaults.json`` and its
  controller :func:`hybridmpm.control.default_method`; the README's first
  screen and ``docs/design.md`` name those defaults, and no sentence of either
  that states a default names a simulator or controller that is not one.
  ``test_the_checks_fail_when_the_defaults_change`` holds that the checks
  catch a change of ``defaults.json`` or of the control table that the pages
  did not follow.
* Its ``bash`` and ``python`` code blocks run as written, in order, in one
  temporary directory (as a reader runs them), with this interpreter's
  environment first on ``PATH``. Left out: the commands that make the virtual
  environment and install the package (``python3 -m venv``, ``. .venv/bin/activate``,
  ``pip install``): they are what ``scripts/test.sh`` does before it runs this
  suite, so the package and every extra the blocks use are installed already;
  and ``bash scripts/test.sh``, which is this suite. ``hybridmpm serve`` runs
  in the background on a free port (the blocks' port 8000 becomes it, in the
  serve block and the blocks that call it), so a run beside another service
  cannot collide, and stops when the module's tests end. Each block's time is
  printed; every block runs within ``BLOCK_TIMEOUT_S``.
"""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

import pytest

from hybridmpm.control import default_method
from hybridmpm.control.controller import DEFAULT_METHODS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DESIGN = ROOT / "docs" / "design.md"
DEFAULTS = ROOT / "python" / "hybridmpm" / "models" / "defaults.json"

#: What the README's table writes for each control method.
METHOD_TEXT = {"pd": "PD", "constant": "constant force", "mpc": "MPC", "diffusion": "diffusion controller", "none": "no control"}
#: The table's bounds.
TABLE_START = "<!-- defaults table:"
TABLE_END = "<!-- end of defaults table -->"
#: Lines of the README a newcomer sees first: they must name the defaults.
FIRST_SCREEN_LINES = 40


# ------------------------------------------------------------------ the defaults


def solver_text(scene: str, config: dict[str, Any]) -> str:
    """The table's text for a default configuration: "MPM at `r_p` = 0.5714, explicit",
    "MPM on 96², projection", "MPM on 48³ at `r_p` = 0.5714, explicit, calibrated" (the integrator
    that steps it: docs/large-step.md); any other kind (a hybrid) by the label ``defaults.json`` gives it."""
    if config["kind"] != "mpm":
        return str(config["label"])
    text = "MPM"
    if config.get("n_grid"):
        text += f" on {config['n_grid']}{'³' if scene.endswith('3d') else '²'}"
    if config.get("r_p", 1.0) != 1.0:
        text += f" at `r_p` = {config['r_p']:g}"
    text += f", {config.get('integrator') or 'explicit'}"  # configurations chosen before the large step ran the explicit one
    return text + (", calibrated" if config.get("calibrated") else "")


def solver_phrase(config: dict[str, Any]) -> str:
    """How prose names a default configuration: "MPM at `r_p`", "MPM on a coarser grid", or its label."""
    if config["kind"] != "mpm":
        return str(config["label"])
    return "MPM on a coarser grid" if config.get("n_grid") else "MPM at `r_p`" if config.get("r_p", 1.0) != 1.0 else "MPM"


def method_phrase(method: str) -> str:
    return f"{METHOD_TEXT[method]} control" if method in ("pd", "mpc") else METHOD_TEXT[method]


class Defaults(NamedTuple):
    configs: dict[str, dict[str, Any]]  # scene -> its default configuration (defaults.json's "config")
    methods: dict[str, str]  # scene -> its default control method

    @classmethod
    def of_the_code(cls) -> Defaults:
        configs = {scene: entry["config"] for scene, entry in json.loads(DEFAULTS.read_text()).items()}
        scenes = sorted(set(configs) | set(DEFAULT_METHODS))
        return cls(configs, {s: default_method(s) for s in scenes})

    def rows(self) -> dict[str, tuple[str, str]]:
        """scene -> (its simulator's text, its controller's text), as the README's table writes them."""
        return {s: (solver_text(s, self.configs[s]) if s in self.configs else "MPM as given", METHOD_TEXT[m]) for s, m in sorted(self.methods.items())}

    def names_of(self, scene: str) -> set[str]:
        """The names of :data:`NAMES` that are ``scene``'s defaults."""
        found = {self.methods[scene]} if scene in self.methods else set()
        c = self.configs.get(scene)
        if c is None:
            return found
        if c["kind"] == "hybrid":
            return found | ({"hybrid", "network"} if c.get("model") else {"hybrid", "coarse grid"})
        if c.get("n_grid"):
            return found | {"coarse grid"}
        return found | ({"mpm_rp"} if c.get("r_p", 1.0) != 1.0 else set())

    def names(self) -> set[str]:
        """The names of :data:`NAMES` that are a default somewhere."""
        return set().union(*(self.names_of(s) for s in self.methods))

    def everywhere(self) -> set[str]:
        """The names of :data:`NAMES` that are a default on every scene."""
        return set.intersection(*(self.names_of(s) for s in self.methods))


#: Simulators and controllers a page could wrongly call a default, and how prose names them.
NAMES = {
    "mpm_rp": r"\bMPM at `r_p`",
    "hybrid": r"\bhybrid\b(?!\.md)",
    "network": r"\b(network|GNS|learned simulator|graph-network|neural)\b",
    "coarse grid": r"\bcoarser? grids?\b|\btwin\b|\b\d+[²³]",
    "diffusion": r"\bdiffusion\b|\bControlNet\b",
    "mpc": r"\bMPC\b|\bmodel-predictive\b",
    "constant": r"\bconstant(-| )force\b",
    "pd": r"\bPD\b",
}
#: A sentence that says what runs by default (not the default of a parameter: "default `r_c = 0.8`", "Defaults: grids 128²").
DEFAULT_CLAIM = re.compile(
    r"\bby default\b|\bdefaults? (simulator|solver|configuration|controller|control|method)s?\b|"
    r"\b(is|are|runs?|as|becomes?|picks?) (the |its |a |each scene's |the scene's )?defaults?\b(?! of `)|\bdefault:",
    re.IGNORECASE,
)
#: A sentence that says something holds on every scene.
EVERY_SCENE = re.compile(r"\bon every scene\b|\beverywhere\b|\bon all scenes\b", re.IGNORECASE)
#: A sentence that says what is *not* the default.
NEGATION = re.compile(r"\b(not|never|no|nor|neither|instead|rather than|loses?|unless)\b", re.IGNORECASE)


def sentences(markdown: str) -> list[str]:
    """The prose of ``markdown`` cut into sentences (and clauses after ';'); each
    line of a code block counts as one, so a command's comment is read too."""
    out: list[str] = []
    prose: list[str] = []
    in_code = False
    for line in markdown.splitlines():
        if line.startswith("```"):
            in_code = not in_code
            continue
        if in_code:
            out.append(line)
        elif line.startswith("|") or not line.strip():
            out += re.split(r"(?<=[.;!?])\s+", " ".join(prose))
            prose = []
            out.append(line)
        else:
            prose.append(line.strip())
    out += re.split(r"(?<=[.;!?])\s+", " ".join(prose))
    return [re.sub(r"\]\([^)]*\)", "]", s) for s in out if s.strip()]  # a link's target is no claim


def table_problems(readme: str, defaults: Defaults) -> list[str]:
    """How the README's defaults table differs from ``defaults``."""
    if TABLE_START not in readme or TABLE_END not in readme:
        return ["README.md has no defaults table (between '<!-- defaults table:' and '<!-- end of defaults table -->')"]
    body = readme.split(TABLE_START, 1)[1].split(TABLE_END, 1)[0]
    rows = {}
    for line in body.splitlines()[1:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = (cells[1], cells[2])
    want = defaults.rows()
    problems = [f"README.md's table: {s} says {rows.get(s)}, the code runs {w}" for s, w in want.items() if rows.get(s) != w]
    return problems + [f"README.md's table: {s} has no default in the code" for s in rows if s not in want]


def statement_problems(name: str, text: str, defaults: Defaults, first_lines: int | None = None) -> list[str]:
    """Whether ``text`` names every default (in its first ``first_lines`` lines when given) and states no other."""
    head = re.sub(r"\s+", " ", "\n".join(text.splitlines()[:first_lines]) if first_lines else text)
    where = f"{name}'s first {first_lines} lines" if first_lines else name
    phrases = {solver_phrase(c) for c in defaults.configs.values()} | {method_phrase(m) for m in defaults.methods.values()}
    problems = [f"{where} do not say {p!r} (a default)" for p in sorted(phrases) if p not in head]
    ours, everywhere = defaults.names(), defaults.everywhere()
    for sentence in sentences(text):
        if NEGATION.search(sentence):
            continue
        if DEFAULT_CLAIM.search(sentence):
            wrong = [n for n, pattern in NAMES.items() if n not in ours and re.search(pattern, sentence)]
            if wrong:
                problems.append(f"{name} states a default it does not run ({', '.join(wrong)}): {sentence.strip()[:200]!r}")
        if EVERY_SCENE.search(sentence):
            wrong = [n for n, pattern in NAMES.items() if n in ours and n not in everywhere and re.search(pattern, sentence)]
            if wrong:
                problems.append(f"{name} says {', '.join(wrong)} on every scene, a default only on some: {sentence.strip()[:200]!r}")
    return problems


def test_the_readme_defaults_table_is_the_codes():
    assert not table_problems(README.read_text(), Defaults.of_the_code())


def test_the_readme_and_design_state_the_defaults_and_no_other():
    d = Defaults.of_the_code()
    problems = statement_problems("README.md", README.read_text(), d, FIRST_SCREEN_LINES)
    problems += statement_problems("docs/design.md", DESIGN.read_text(), d)
    assert not problems, "\n".join(problems)


def test_the_checks_fail_when_the_defaults_change():
    d = Defaults.of_the_code()
    readme, design = README.read_text(), DESIGN.read_text()
    # defaults.json changed: water2d on 96² (a coarser grid), and a hybrid on water3d
    configs = {s: dict(c) for s, c in d.configs.items()}
    configs["water2d"] |= {"kind": "mpm", "n_grid": 96, "r_p": 1.0}
    configs["water3d"] |= {"kind": "hybrid", "label": "hybrid, default (error rule, tol 2 g)", "model": "water3d.onnx"}
    changed = Defaults(configs, d.methods)
    assert any("water2d" in p for p in table_problems(readme, changed))
    assert any("water3d" in p for p in table_problems(readme, changed))
    assert any("MPM on a coarser grid" in p for p in statement_problems("docs/design.md", design, changed))
    assert any("mpm_rp on every scene" in p for p in statement_problems("README.md", readme, changed, FIRST_SCREEN_LINES))
    # the control table changed: diffusion on sand2d
    methods = d.methods | {"sand2d": "diffusion"}
    changed = Defaults(d.configs, methods)
    assert any("sand2d" in p for p in table_problems(readme, changed))
    assert any("pd on every scene" in p for p in statement_problems("README.md", readme, changed, FIRST_SCREEN_LINES))
    assert any("pd on every scene" in p for p in statement_problems("docs/design.md", design, changed))
    # the old wording of the front door is caught
    old = "A learned simulator runs by default. Sketches go to the diffusion controller by default."
    problems = statement_problems("old", f"plain MPM at `r_p` and PD control. {old}", d)
    assert len(problems) == 2 and "network" in problems[0] and "diffusion" in problems[1], problems


# ------------------------------------------------------------------ the code blocks


class Block(NamedTuple):
    lang: str
    line: int
    code: str


def code_blocks(markdown: str) -> list[Block]:
    """The ``bash`` and ``python`` fenced blocks of ``markdown``, in order."""
    found, lang, start, lines = [], None, 0, []
    for i, line in enumerate(markdown.splitlines(), 1):
        if lang is None and line.startswith("```") and line[3:].strip():
            lang, start, lines = line[3:].strip(), i, []
        elif lang is not None and line.startswith("```"):
            if lang in ("bash", "python"):
                found.append(Block(lang, start, "\n".join(lines) + "\n"))
            lang = None
        elif lang is not None:
            lines.append(line)
    return found


#: Commands of the setup that scripts/test.sh has already done (module doc).
_SETUP = re.compile(r"^(python3? -m venv |\. \.venv/bin/activate$|(python3? -m )?pip install )")
#: The README's service port, replaced by a free one.
_PORT = "8000"
#: The most a block may take, in seconds.
BLOCK_TIMEOUT_S = 900


def runnable(code: str) -> str:
    """``code`` without the setup commands (each a whole line or a part of an ``&&`` chain)."""
    out = []
    for line in code.splitlines():
        parts = [p for p in line.split(" && ") if not _SETUP.match(p.strip())]
        if parts:
            out.append(" && ".join(parts))
    return "\n".join(out) + "\n"


BLOCKS = code_blocks(README.read_text())
#: The blocks run here: all but ``bash scripts/test.sh`` (the suite this test is part of; CI runs it itself).
RUN = [b for b in BLOCKS if b.code.strip() != "bash scripts/test.sh"]


def _environment() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTHONPATH", None)
    return env


@pytest.fixture(scope="module")
def workdir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("readme")


@pytest.fixture(scope="module")
def service(workdir: Path) -> Iterator[dict[str, Any]]:
    """A lazily started ``hybridmpm serve`` (the README's serve block, on a free port)."""
    state: dict[str, Any] = {}
    yield state
    proc = state.get("proc")
    if proc is not None:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        state["log"].close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_service(service: dict[str, Any], workdir: Path) -> int:
    if "port" in service:
        return int(service["port"])
    serve = next(b for b in BLOCKS if "hybridmpm serve" in b.code)
    command = next(ln for ln in serve.code.splitlines() if "hybridmpm serve" in ln).split("#", 1)[0].strip()
    port = _free_port()
    assert f"--port {_PORT}" in command, command
    log = (workdir / "serve.log").open("w")
    proc = subprocess.Popen(["bash", "-c", f"exec {command.replace(_PORT, str(port))}"], cwd=workdir, env=_environment(), stdout=log, stderr=log)
    service.update(proc=proc, log=log, port=port)
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5) as r:
                assert r.status == 200
                break
        except OSError:
            assert proc.poll() is None, (workdir / "serve.log").read_text()
            assert time.monotonic() < deadline, "hybridmpm serve did not answer in 120 s"
            time.sleep(0.5)
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as r:  # the page
        assert r.status == 200 and b"<html" in r.read().lower()
    return port


def test_the_readme_is_a_front_door_of_at_most_200_lines():
    """The README says what runs and where to read on; the rest lives in docs/."""
    lines = README.read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines"


def test_the_readme_has_code_blocks_to_run():
    assert len(BLOCKS) - len(RUN) == 1, "README.md names `bash scripts/test.sh` in a block of its own, once"
    assert len(RUN) >= 6 and any(b.lang == "python" for b in RUN) and any("hybridmpm serve" in b.code for b in RUN)


@pytest.mark.parametrize("block", RUN, ids=[f"README.md:{b.line}-{b.lang}" for b in RUN])
def test_the_readme_code_block_runs_as_written(block: Block, workdir: Path, service: dict[str, Any]):
    t0 = time.perf_counter()
    if "hybridmpm serve" in block.code:
        _start_service(service, workdir)
    else:
        code = runnable(block.code)
        if f"localhost:{_PORT}" in code:
            code = code.replace(f"localhost:{_PORT}", f"localhost:{_start_service(service, workdir)}")
        argv = ["bash", "-e", "-c", code] if block.lang == "bash" else [sys.executable, "-c", code]
        r = subprocess.run(argv, cwd=workdir, env=_environment(), capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
        assert r.returncode == 0, f"README.md:{block.line} failed ({r.returncode}):\n{code}\n--- stdout\n{r.stdout[-3000:]}\n--- stderr\n{r.stderr[-3000:]}"
    print(f"README.md:{block.line} ({block.lang}): {time.perf_counter() - t0:.1f} s")
