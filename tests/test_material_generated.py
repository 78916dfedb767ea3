"""A model of the core needs no Python: its material class, its parameter-set class, its scene-level table,
its GNS particle type, its scene-block keys and its pour body's keys are all made from the core's schema
(``_core.material_schema()``) and codes (``_core.MATERIAL_CODES``). Here the generators are fed a schema
with a sixth, synthetic model ``foam`` (a density and two numbers), and the package's tables are given its
made classes as the import gives those of a model of the core; nothing calls the Rust solver with it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridmpm import conventions
from hybridmpm.conventions import GNS_TYPE_OF_MATERIAL, MATERIALS, gns_types
from hybridmpm.errors import InvalidInputError
from hybridmpm.materials import MODELS, WRITTEN, _Material, material_classes, material_from_block, scene_bases
from hybridmpm.mpm import MpmParams
from hybridmpm.mpm.schema import SCHEMA, Param
from hybridmpm.mpm.sets import SET_CLASSES, set_classes


def _row(name: str, key: str, unit: str, default: float, lower: float, upper: float | None, rng: str, what: str) -> Param:
    return Param(
        name=name,
        key=key,
        unit=unit,
        lower=lower,
        lower_inclusive=upper is not None,
        upper=upper,
        upper_inclusive=True if upper is not None else None,
        choices=(),
        range=rng,
        default=default,
        description=what,
        source="a test's synthetic model",
    )


FOAM = (
    _row("density", "density", "kg/m³", 50.0, 0.0, None, "> 0", "rest density ρ of the foam"),
    _row("stiffness", "foam_k", "Pa", 1.0e4, 0.0, None, "> 0", "the foam's stiffness"),
    _row("damping", "foam_c", "-", 0.1, 0.0, 1.0, "in [0, 1]", "the foam's damping ratio"),
)
CODE = len(MATERIALS)


@pytest.fixture
def foam(monkeypatch):
    """The classes made for a schema with ``foam`` at code ``len(MATERIALS)``, put in the package's
    tables as the import puts those of a model of the core: ``(Foam, FoamParams)``."""
    schema = {**SCHEMA, "foam": FOAM}
    codes = {**MATERIALS, "foam": CODE}
    sets = set_classes(schema)
    models = material_classes(schema, codes)
    # the five written classes stay the package's own; only foam is made
    assert all(models[m] is WRITTEN[m] and sets[m] is SET_CLASSES[m] for m in MATERIALS)
    monkeypatch.setitem(SCHEMA, "foam", FOAM)
    monkeypatch.setitem(MATERIALS, "foam", CODE)
    monkeypatch.setitem(GNS_TYPE_OF_MATERIAL, CODE, gns_types(codes)[CODE])
    monkeypatch.setitem(SET_CLASSES, "foam", sets["foam"])
    monkeypatch.setitem(MODELS, "foam", models["foam"])
    return models["foam"], sets["foam"]


def test_a_sixth_model_gets_a_frozen_material_class_with_the_schemas_keys_defaults_and_descriptions(foam):
    Foam, FoamParams = foam
    assert issubclass(Foam, _Material) and Foam.__name__ == "Foam" and (Foam.name, Foam.code) == ("foam", CODE)
    assert [f.name for f in dataclasses.fields(Foam)] == ["density", "foam_k", "foam_c"]
    assert dataclasses.asdict(Foam()) == {"density": 50.0, "foam_k": 1.0e4, "foam_c": 0.1}
    with pytest.raises(dataclasses.FrozenInstanceError):
        Foam().foam_k = 2.0  # type: ignore[misc]
    assert all(p.description in (Foam.__doc__ or "") and p.key in (Foam.__doc__ or "") for p in FOAM)
    assert FoamParams.__name__ == "FoamParams"
    assert dataclasses.asdict(FoamParams()) == {"density": 50.0, "stiffness": 1.0e4, "damping": 0.1}


def test_a_sixth_models_block_is_checked_naming_the_users_key_and_value(foam):
    Foam, _ = foam
    with pytest.raises(InvalidInputError) as e:
        material_from_block("foam", {"foam_k": -1.0}, "blocks[0]")
    assert e.value.field == "blocks[0].foam_k"
    assert str(e.value).startswith("blocks[0].foam_k: must be > 0, got -1.0"), e.value
    with pytest.raises(InvalidInputError) as e:
        material_from_block("foam", {"foam_c": 1.5}, "blocks[2]")
    assert str(e.value).startswith("blocks[2].foam_c: must be in [0, 1], got 1.5"), e.value
    with pytest.raises(InvalidInputError) as e:
        material_from_block("foam", {"E": 1e5}, "blocks[1]")  # another model's key
    assert e.value.field == "blocks[1].E" and "foam_k" in str(e.value)
    assert material_from_block("foam", {"foam_k": 2.0e4}, "blocks[0]") == Foam(foam_k=2.0e4)


def test_a_sixth_models_material_and_parameter_set_round_trip(foam):
    Foam, FoamParams = foam
    m = Foam(density=80.0, foam_k=3.0e4, foam_c=0.25)
    ps = m.to_params()
    assert type(ps) is FoamParams and (ps.density, ps.stiffness, ps.damping) == (80.0, 3.0e4, 0.25)
    assert Foam.from_params(ps) == m


def test_a_sixth_models_scene_table_round_trips_through_the_parameter_dict(foam):
    Foam, FoamParams = foam
    params = MpmParams(tables={"foam": FoamParams(stiffness=2.0e4)})
    assert MpmParams().table("foam") == FoamParams()  # the default table of a model without a field
    d = params.to_dict()
    assert d["foam"] == {"density": 50.0, "stiffness": 2.0e4, "damping": 0.1}
    assert list(d).index("foam") == list(d).index("viscoplastic") + 1  # in code order, before the further sets
    back = MpmParams.from_dict(d)
    assert back.tables == params.tables and back.to_dict() == d
    # the scene's table is the base of a block naming the model, and a particle of it indexes its code
    assert scene_bases(params)["foam"] == Foam(foam_k=2.0e4)
    assert material_from_block("foam", {"foam_c": 0.5}, "blocks[0]", scene_bases(params)) == Foam(foam_k=2.0e4, foam_c=0.5)
    assert params.set_index(FoamParams(stiffness=2.0e4)) == CODE
    assert params.set_index(FoamParams(stiffness=5.0e4)) is None
    with pytest.raises(InvalidInputError) as e:
        MpmParams(tables={"foam": FoamParams(damping=2.0)}).validate()
    assert e.value.field == "foam.damping"
    with pytest.raises(InvalidInputError) as e:
        MpmParams(tables={"water": FoamParams()}).validate()  # a model with a field of its own
    assert e.value.field == "tables"


def test_a_sixth_model_gets_a_gns_type_past_the_named_ones_and_a_rest_density(foam):
    codes = {**MATERIALS}
    types = gns_types(codes)
    assert types[CODE] == max(gns_types({k: v for k, v in codes.items() if k != "foam"}).values()) + 1
    assert gns_types(codes) == types  # the same on every call
    assert {c: t for c, t in types.items() if c != CODE} == {c: t for c, t in conventions.GNS_TYPE_OF_MATERIAL.items() if c != CODE}
    from hybridmpm.render.surface_scene import rest_densities

    rho = rest_densities(MpmParams(), np.array([types[CODE], conventions.GNS_WATER]))
    assert rho.tolist() == [50.0, MpmParams().water.density]


def test_a_sixth_models_pour_body_takes_its_keys(foam):
    pytest.importorskip("fastapi")
    from pydantic import ValidationError

    from hybridmpm.service.schemas import block_pour_model

    Foam, _ = foam
    BlockPour = block_pour_model(SCHEMA)
    body = BlockPour.model_validate({"material": "foam", "lo": [0.4, 0.4], "hi": [0.5, 0.5], "foam_k": 2.0e4, "params": {"foam_c": 0.3}})
    block = body.model_dump(exclude_none=True)
    keys = {**{k: v for k, v in block.items() if k not in ("material", "lo", "hi", "velocity", "params")}, **block["params"]}
    assert keys == {"foam_k": 2.0e4, "foam_c": 0.3}
    assert material_from_block(block["material"], keys, "block") == Foam(foam_k=2.0e4, foam_c=0.3)
    assert "the foam's stiffness" in BlockPour.model_json_schema()["properties"]["foam_k"]["description"]
    with pytest.raises(ValidationError):
        BlockPour.model_validate({"material": "foam", "lo": [0.4, 0.4], "hi": [0.5, 0.5], "foam_k": "stiff"})
