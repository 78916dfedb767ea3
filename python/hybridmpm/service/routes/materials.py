"""Materials: ``GET /v1/materials`` gives every model's parameter schema, the core's one table
(:data:`hybridmpm.mpm.schema.SCHEMA`, from ``_core.material_schema()``), and the presets a pour's
``material`` names (:data:`hybridmpm.materials.PRESETS`), so that a client builds a pour
(``POST /v1/sessions/{sid}/blocks``) and checks its ranges from what the server runs."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from fastapi import APIRouter

from hybridmpm.materials import PRESET_SOURCES, PRESETS
from hybridmpm.mpm.schema import SCHEMA
from hybridmpm.service.schemas import MaterialsInfo

router = APIRouter()


def materials_info() -> dict[str, Any]:
    """``{"models": {model: [param, ...]}, "presets": {name: {"model", "params", "source"}}}``: each
    model's rows of :data:`~hybridmpm.mpm.schema.SCHEMA` as dicts (:class:`~hybridmpm.mpm.schema.Param`'s
    fields), and each preset's model, its parameters by the user's key and their source."""
    return {
        "models": {model: [asdict(p) for p in params] for model, params in SCHEMA.items()},
        "presets": {name: {"model": m.name, "params": asdict(m), "source": PRESET_SOURCES[name]} for name, m in PRESETS.items()},
    }


@router.get("/v1/materials", response_model=MaterialsInfo)
async def materials() -> dict[str, Any]:
    """Every model's parameters (name, the user's key, unit, range with its inclusivity, choices,
    default, description, source) and the presets a pour takes. A pour names a model or a preset in
    ``material`` and overrides any parameter by its key (``params`` or flat keys)."""
    return materials_info()
