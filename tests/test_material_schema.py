"""A material's parameters are declared once, in the Rust core's schema (each model's file in ``rust/mpm/src/material/``, exported as
``_core.material_schema()``): Python's materials, the parameter-dict dataclasses, the HTTP pour body and the
tables of docs/materials.md follow it, and every range is checked from it, as the user's value in float64
and then in float32, so that what Python accepts the core accepts."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from hybridmpm import _core
from hybridmpm.conventions import MATERIALS
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import F32_TINY
from hybridmpm.materials import MODELS, material_from_block
from hybridmpm.mpm import MpmParams
from hybridmpm.mpm.params import SET_CLASSES, ElasticParams
from hybridmpm.mpm.schema import SCHEMA, Param

DOCS = Path(__file__).resolve().parents[1] / "docs" / "materials.md"


def test_the_schema_lists_every_model_and_its_structs_fields_and_defaults():
    assert list(SCHEMA) == list(MATERIALS)
    defaults = _core.default_params(2)
    for model, params in SCHEMA.items():
        assert [p.name for p in params] == [f.name for f in dataclasses.fields(SET_CLASSES[model])], model
        assert {p.name: p.default for p in params} == defaults[model], model
        for p in params:
            assert p.default in p.choices if p.choices else p.contains(p.default), (model, p)


def test_the_material_classes_take_the_schemas_keys_and_defaults():
    for model, cls in MODELS.items():
        assert [f.name for f in dataclasses.fields(cls)] == [p.key for p in SCHEMA[model]], model
        assert dataclasses.asdict(cls()) == {p.key: p.default for p in SCHEMA[model]}, model
    keys = {p.name: p.key for p in SCHEMA["elastic"]}
    assert keys["youngs_modulus"] == "E" and keys["poisson_ratio"] == "nu" and keys["density"] == "density"


def test_nu_just_below_a_half_that_float32_rounds_to_a_half_is_refused_naming_the_users_key_and_value():
    nu = 0.49999999
    assert nu < 0.5 and float(np.float32(nu)) == 0.5
    for check, field in [
        (lambda: MODELS["elastic"](nu=nu).validate(), "nu"),
        (lambda: material_from_block("jello", {"nu": nu}, "blocks[0]"), "blocks[0].nu"),
        (lambda: MpmParams(elastic=ElasticParams(poisson_ratio=nu)).validate(), "elastic.poisson_ratio"),
        (lambda: MpmParams(sets=[ElasticParams(poisson_ratio=nu)]).validate(), "sets[0].elastic.poisson_ratio"),
    ]:
        with pytest.raises(InvalidInputError) as e:
            check()
        assert e.value.field == field
        assert str(e.value).startswith(f"{field}: must be in [0, 0.5), got {nu!r}"), e.value
    # the largest float32 below 0.5 is in the range in both precisions: Python and the core accept it
    below = float(np.nextafter(np.float32(0.5), np.float32(0)))
    assert MODELS["elastic"](nu=below).validate() is None
    _core.MpmSolver(MpmParams(n_grid=16, sets=[ElasticParams(poisson_ratio=below)]).to_dict())


def test_a_number_float32_rounds_to_zero_or_past_its_range_is_judged_by_its_rounding():
    """``nu = 1e-110`` is 0 in float32, inside [0, 0.5): accepted by Python and the core alike (a hypothesis
    draw of the limits tests found Python refusing it once); ``density = 1e-300`` is 0 there, outside
    ``> 0``; ``E = 1e39`` is infinite there: both refused naming the user's key and value."""
    from hybridmpm.mpm.params import SandParams

    assert material_from_block("sand", {"nu": 1e-110}, "blocks[0]") is not None
    params = MpmParams(n_grid=16, sand=SandParams(poisson_ratio=1e-110), sets=[ElasticParams(poisson_ratio=1e-300)])
    params.validate()
    _core.MpmSolver(params.to_dict())
    for key, value, words in (("density", 1e-300, "0.0 in float32"), ("E", 1e39, "past float32's largest number")):
        with pytest.raises(InvalidInputError) as e:
            material_from_block("jello", {key: value}, "blocks[1]")
        assert e.value.field == f"blocks[1].{key}" and repr(value) in str(e.value) and words in str(e.value), e.value


def _bounds() -> list[tuple[str, Param, str]]:
    return [(m, p, side) for m, ps in SCHEMA.items() for p in ps for side in ("lower", "upper") if getattr(p, side) is not None]


def _just_outside(p: Param, side: str) -> float:
    b, inclusive = getattr(p, side), getattr(p, f"{side}_inclusive")
    outward = -np.inf if side == "lower" else np.inf
    return float(np.nextafter(b, outward)) if inclusive else float(b)


def _just_inside(p: Param, side: str) -> float:
    """The float32 next to the bound on its inside (the bound when inclusive), a normal float32."""
    b, inclusive = getattr(p, side), getattr(p, f"{side}_inclusive")
    if inclusive:
        return float(b)
    inward = np.float32(np.inf if side == "lower" else -np.inf)
    x = float(np.nextafter(np.float32(b), inward))
    return float(np.copysign(F32_TINY, x)) if 0 < abs(x) < F32_TINY else x


@pytest.mark.parametrize(("model", "p", "side"), _bounds(), ids=lambda x: x.name if isinstance(x, Param) else str(x))
def test_just_outside_each_bound_python_refuses_naming_the_users_key_and_just_inside_the_core_accepts(model, p, side):
    outside, inside = _just_outside(p, side), _just_inside(p, side)
    with pytest.raises(InvalidInputError) as e:
        material_from_block(model, {p.key: outside}, "blocks[3]")
    assert e.value.field == f"blocks[3].{p.key}"
    assert str(e.value).startswith(f"blocks[3].{p.key}: must be {p.range}, got {outside!r}"), e.value
    m = material_from_block(model, {p.key: inside}, "blocks[3]")
    # the core takes it, as a parameter set of the table and as the model's default set
    params = MpmParams(n_grid=16, sets=[m.to_params()], **{model: m.to_params()})
    _core.MpmSolver(params.to_dict())
    # and refuses the value just outside on its own (the dict straight to the core), naming the field
    if float(np.float32(outside)) == outside:
        d = MpmParams(n_grid=16).to_dict()
        d["sets"] = [{model: {p.name: outside}}]
        with pytest.raises(InvalidInputError) as e:
            _core.MpmSolver(d)
        assert e.value.field == f"sets[0].{model}.{p.name}"


def test_every_model_has_bounds_to_check():
    assert {m for m, _, _ in _bounds()} == set(SCHEMA)
    assert len(_bounds()) >= 20


def _doc_tables() -> dict[str, list[list[str]]]:
    """Each model's parameter table in docs/materials.md (``| key | symbol | unit | default | range |``), by
    the ``material = "..."`` of the heading above it (a heading naming two models: its tables in order)."""
    tables: dict[str, list[list[str]]] = {}
    models: list[str] = []
    rows: list[list[str]] | None = None
    for line in DOCS.read_text().splitlines() + [""]:
        if line.startswith("#"):
            models = re.findall(r'material = "(\w+)"', line)
        elif line.startswith("| key | symbol | unit | default"):
            rows = []
        elif rows is not None and line.startswith("|") and not line.startswith("|---"):
            rows.append([c.strip().strip("`") for c in line.strip("|").split("|")])
        elif rows is not None and not line.startswith("|"):
            tables[models.pop(0)] = rows
            rows = None
    return tables


def test_the_docs_parameter_tables_are_the_schema():
    tables = _doc_tables()
    assert set(tables) == set(SCHEMA)
    for model, params in SCHEMA.items():
        rows = {r[0]: r for r in tables[model]}
        assert list(rows) == [p.key for p in params], model
        for p in params:
            key, _symbol, unit, default, rng = rows[p.key]
            assert unit == p.unit, (model, key)
            assert rng == p.range, (model, key)
            assert (default if p.choices else float(default)) == p.default, (model, key)
