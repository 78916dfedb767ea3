"""The service keeps the architecture's rules (docs/architecture.md): routes
read a session's facts, one session core does a session's work, the local and
the Ray backends stand side by side on one protocol, each rule of a session is
written once, and the page takes the particle-type codes from the conventions."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest
from _arch import PACKAGE, ROOT, SERVICE, STATIC


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


def test_no_class_stands_in_for_a_simulator_in_the_service():
    # the service holds real simulators (local sessions, actors) or none (a Ray front end's session has sim=None)
    offenders = []
    for p in sorted((PACKAGE / "service").rglob("*.py")):
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and ("Sim" in node.name and "View" in node.name or node.name.endswith("Simulator")):
                offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: class {node.name}")
    assert not offenders, "\n".join(offenders)


# ------------------------------------------------------------------ the session backends


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
