"""The solver's parameters have one schema, the Rust core's.

The binding reads the parameter dict with the core's types (``SolverParams``,
``ColliderParams`` and their serde derives) and Python takes its dataclass
defaults from ``_core.default_params``: the names and the defaults must agree
everywhere, and an unknown key is refused wherever it is, naming it.

The connectivity radius of the radius graph is written once too, as a const of
the neighbour-search crate that Python reads as ``_core.CONNECTIVITY_RADIUS``.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import get_args

import numpy as np
import pytest

from hybridmpm import _core
from hybridmpm.conventions import CONNECTIVITY_RADIUS, DEFAULT_N_GRID
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import WALL_FACES, Box, Condition, MpmParams, MpmSolver, SandParams, Sphere, WallFace, WallParams, WaterParams


def fields(cls: type) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


@pytest.mark.parametrize("dim", [2, 3])
def test_python_defaults_are_the_rust_defaults(dim):
    rust = _core.default_params(dim)
    assert MpmParams(dim=dim).to_dict() == rust
    assert list(MpmParams(dim=dim).to_dict()) == list(rust)  # same names, same order
    assert DEFAULT_N_GRID[dim] == rust["n_grid"]
    # the bits, not just equal floats: Rust's f32 defaults arrive as their decimals
    assert repr(MpmParams(dim=dim).to_dict()) == repr(rust)


def test_dataclass_fields_are_the_rust_keys():
    rust = _core.default_params(2)
    # bodies: written only when there are some; integrator: only when not the default; a model without a
    # field of its own has its table in `tables`, written under the model's name
    further = list(MpmParams().tables)
    assert [f for f in fields(MpmParams) if f != "tables"] == [*(k for k in rust if k not in further), "bodies", "integrator"]
    assert fields(MpmParams).index("tables") == fields(MpmParams).index("sets") - 1
    assert "integrator" not in rust and MpmParams().integrator == _core.INTEGRATORS[0]
    assert fields(WaterParams) == list(rust["water"])
    assert fields(SandParams) == list(rust["sand"])
    # faces: written only when some face is overridden
    assert fields(WallParams) == [*rust["walls"], "faces"]
    assert fields(WallFace) == ["condition", "friction"]
    collider = _core.default_collider()
    for cls in (Box, Sphere):
        defaults = {f.name: f.default for f in dataclasses.fields(cls) if f.name in collider}
        assert defaults == collider


def test_dimension_free_defaults_are_the_same_in_2d_and_3d():
    d2, d3 = _core.default_params(2), _core.default_params(3)
    for key in ("cfl", "substeps", "max_substeps", "num_threads", "water", "sand", "walls"):
        assert d2[key] == d3[key], key
    assert d3["gravity"] == [0.0, -9.8, 0.0]


def test_default_params_refuses_another_dim():
    with pytest.raises(InvalidInputError) as e:
        _core.default_params(4)
    assert e.value.field == "dim"


def test_the_defaults_reach_the_solver():
    for dim in (2, 3):
        sim = MpmSolver(MpmParams(dim=dim))
        assert sim.n_grid == _core.default_params(dim)["n_grid"]
        # the dict of defaults is a valid parameter dict
        assert _core.MpmSolver(_core.default_params(dim)).n_grid == sim.n_grid


@pytest.mark.parametrize(
    "params, field",
    [
        ({"wter": {}}, "wter"),
        ({"wter": None}, "wter"),
        ({"water": {"bulk": 1.0}}, "water.bulk"),
        ({"sand": {"phi": 30.0}}, "sand.phi"),
        ({"walls": {"roughness": 1.0}}, "walls.roughness"),
        ({"walls": {"faces": {"y-": {"mu": 0.1}}}}, "walls.faces.y-.mu"),
        ({"walls": {"faces": {"floor": {}}}}, "walls.faces.floor"),
        ({"colliders": [{"shape": "sphere", "center": [0.5, 0.5], "radius": 0.1, "spin": 1.0}]}, "colliders[0].spin"),
    ],
)
def test_an_unknown_key_is_refused_naming_it(params, field):
    with pytest.raises(InvalidInputError) as e:
        _core.MpmSolver({"dim": 2, **params})
    assert e.value.field == field, str(e.value)
    assert str(e.value).startswith(f"{field}: unknown parameter (allowed: ")


def test_the_top_level_names_every_allowed_key():
    with pytest.raises(InvalidInputError) as e:
        _core.MpmSolver({"dim": 2, "wter": {}})
    keys = [k for k in _core.default_params(2) if k != "colliders"]
    assert str(e.value) == "wter: unknown parameter (allowed: " + ", ".join([*keys, "integrator", "colliders", "bodies"]) + ")"


@pytest.mark.parametrize(
    "params, field",
    [
        ({"water": {"density": "1000"}}, "water.density"),
        ({"water": {"density": True}}, "water.density"),
        ({"water": 3}, "water"),
        ({"gravity": [0.0, -9.8, 0.0]}, "gravity"),
        ({"gravity": [0.0, "down"]}, "gravity[1]"),
        ({"walls": {"cells": 3.0}}, "walls.cells"),
        ({"walls": {"condition": "glue"}}, "walls.condition"),
        ({"walls": {"faces": {"y-": 0.3}}}, "walls.faces.y-"),
        ({"colliders": [{"shape": "cube", "center": [0.5, 0.5]}]}, "colliders[0].shape"),
        ({"colliders": [{"center": [0.5, 0.5], "radius": 0.1}]}, "colliders[0].shape"),
        ({"colliders": [{"shape": "box", "center": [0.5, 0.5]}]}, "colliders[0].half_extents"),
        ({"colliders": [{"shape": "sphere", "center": [0.5], "radius": 0.1}]}, "colliders[0].center"),
        ({"colliders": [{"shape": "circle", "center": [0.5, 0.5], "radius": 0.1, "friction": "rough"}]}, "colliders[0].friction"),
        ({"colliders": [3]}, "colliders[0]"),
    ],
)
def test_a_bad_value_names_its_field(params, field):
    with pytest.raises(InvalidInputError) as e:
        _core.MpmSolver({"dim": 2, **params})
    assert e.value.field == field, str(e.value)
    assert isinstance(e.value, ValueError)


def test_none_is_a_missing_key():
    sim = _core.MpmSolver({"dim": 2, "n_grid": None, "cfl": None, "water": None, "walls": {"faces": {"y-": {"friction": None}}}, "colliders": None})
    assert sim.n_grid == _core.default_params(2)["n_grid"]


def test_every_face_and_condition_python_names_is_a_rust_one():
    conditions = get_args(Condition)
    faces = {name: {"condition": c} for name, c in zip(WALL_FACES, conditions * 2)}
    _core.MpmSolver({"dim": 3, "n_grid": 32, "walls": {"faces": faces}})
    for condition in conditions:
        _core.MpmSolver({"dim": 2, "walls": {"condition": condition}, "colliders": [Sphere([0.5, 0.5], 0.1, condition=condition).to_dict()]})


# ----------------------------------------------------------------- the connectivity radius
ROOT = Path(__file__).resolve().parents[1]
#: The value as a number in source: not part of a longer number (0.0150, 0.015625, 10.015).
RADIUS_LITERAL = re.compile(r"(?<![\d.])0\.015(?![\d])")
#: Its one definition, in rust/neighbors/src/lib.rs.
RADIUS_DEFINITION = "pub const CONNECTIVITY_RADIUS: f32 = 0.015;"


def radius_literals(root: Path) -> tuple[list[str], int]:
    """Lines of ``root``'s python/ (.py, .pyi) and rust/*/src (.rs) trees that write
    the connectivity radius's value, code or comment, and how many are its one
    definition (left out of the list). Tests are left out (a ``tests`` folder,
    ``tests.rs``); benches and docs lie outside these trees."""
    files = [*(root / "python").rglob("*.py"), *(root / "python").rglob("*.pyi"), *(root / "rust").glob("*/src/**/*.rs")]
    found, definitions = [], 0
    for p in sorted(files):
        rel = p.relative_to(root)
        if "tests" in rel.parts or p.name == "tests.rs":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if not RADIUS_LITERAL.search(line):
                continue
            if line.strip() == RADIUS_DEFINITION:
                definitions += 1
            else:
                found.append(f"{rel}:{i}: {line.strip()}")
    return found, definitions


def test_the_connectivity_radius_is_the_rust_one():
    assert CONNECTIVITY_RADIUS == _core.CONNECTIVITY_RADIUS
    assert type(CONNECTIVITY_RADIUS) is float
    # the f32's shortest decimal, as serde gives the solver's defaults; not the f32 widened
    assert repr(CONNECTIVITY_RADIUS) == str(np.float32(_core.CONNECTIVITY_RADIUS))
    # and radius_graph's default: particles one f32 step apart around R from particle 0
    r32 = np.float32(CONNECTIVITY_RADIUS)
    xs = [r32]
    for _ in range(8):
        xs = [np.nextafter(xs[0], np.float32(0)), *xs, np.nextafter(xs[-1], np.float32(1))]
    pos = np.array([[0.0, 0.0]] + [[x, 0.0] for x in xs], np.float32)

    def degree(*radius: float) -> int:
        return int((_core.radius_graph(pos, *radius)[1] == 0).sum())

    default = degree()
    assert default == degree(CONNECTIVITY_RADIUS) == 10  # itself and the 9 at most R away
    assert degree(float(np.nextafter(r32, np.float32(0)))) == default - 1
    assert degree(float(np.nextafter(r32, np.float32(1)))) == default + 1


def test_the_connectivity_radius_is_written_once():
    found, definitions = radius_literals(ROOT)
    assert definitions == 1, f"{definitions} definitions of the connectivity radius (expected one: {RADIUS_DEFINITION})"
    assert not found, "the connectivity radius restated (name CONNECTIVITY_RADIUS instead):\n" + "\n".join(found)


def test_the_radius_scan_finds_a_restated_value(tmp_path):
    files = {
        "python/pkg/m.py": "R = 0.015\nN = 0.015625  # another number\n",
        "python/pkg/_ext.pyi": "def f(radius: float = 0.015) -> None: ...\n",
        "python/pkg/tests/test_m.py": "R = 0.015\n",
        "rust/c/src/lib.rs": f"{RADIUS_DEFINITION}\n/// Default `0.015`.\n",
        "rust/c/src/deep/graph.rs": "#[pyo3(signature = (radius = 0.015))]\n",
        "rust/c/src/relax/tests.rs": "let b = [0.0f32, 0.015];\n",
        "rust/c/benches/b.rs": "radius: 0.015,\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    found, definitions = radius_literals(tmp_path)
    assert definitions == 1
    assert [f.split(": ", 1)[0] for f in found] == ["python/pkg/_ext.pyi:1", "python/pkg/m.py:1", "rust/c/src/deep/graph.rs:1", "rust/c/src/lib.rs:2"]
