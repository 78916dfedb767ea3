"""Each constitutive model's parameter set (the dataclass of one entry of the solver's table, by the
parameter dict's names: ``youngs_modulus``, ``poisson_ratio``, ...), one per model of the core's schema
(:data:`hybridmpm.mpm.schema.SCHEMA`). Water, sand, the elastic solid, snow and the viscoplastic solid
have written classes (typed for mypy and the docs; tests/test_material_schema.py holds each to the
schema); every other model of the core gets one made from its schema rows (:func:`set_classes`), so
that a model added to the core needs no Python. Defaults are the Rust core's
(``SolverParams::default()``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, make_dataclass

from hybridmpm import _core
from hybridmpm.mpm.schema import SCHEMA, Param

_SOLVER = _core.default_params(2)  # the sets are the same in 3D (tests/test_one_schema.py)
_WATER, _SAND = _SOLVER["water"], _SOLVER["sand"]
_ELASTIC, _SNOW, _VISCO = _SOLVER["elastic"], _SOLVER["snow"], _SOLVER["viscoplastic"]


@dataclass
class WaterParams:
    """Weakly compressible water. ``density`` ρ [kg/m³], ``bulk_modulus`` K [Pa]
    (sound speed ``sqrt(K/ρ)``, default 20 m/s), ``viscosity`` η [Pa·s].
    Defaults are the Rust core's (``WaterParams::default()``)."""

    density: float = _WATER["density"]
    bulk_modulus: float = _WATER["bulk_modulus"]
    viscosity: float = _WATER["viscosity"]


@dataclass
class SandParams:
    """Drucker–Prager sand. ``youngs_modulus`` E [Pa], ``poisson_ratio`` ν,
    ``friction_angle_deg`` φ [°], ``cohesion`` c [Pa] (cone apex at mean
    stress ``c / tan φ``), ``density`` ρ [kg/m³]. Defaults are the Rust
    core's (``SandParams::default()``)."""

    density: float = _SAND["density"]
    youngs_modulus: float = _SAND["youngs_modulus"]
    poisson_ratio: float = _SAND["poisson_ratio"]
    friction_angle_deg: float = _SAND["friction_angle_deg"]
    cohesion: float = _SAND["cohesion"]


@dataclass
class ElasticParams:
    """Elastic solid. ``density`` ρ [kg/m³], ``youngs_modulus`` E [Pa],
    ``poisson_ratio`` ν in [0, 0.5), ``model``: ``"corotated"`` (fixed-corotated,
    Stomakhin et al. 2012) or ``"neohookean"``. Defaults are the Rust core's."""

    density: float = _ELASTIC["density"]
    youngs_modulus: float = _ELASTIC["youngs_modulus"]
    poisson_ratio: float = _ELASTIC["poisson_ratio"]
    model: str = _ELASTIC["model"]


@dataclass
class SnowParams:
    """Snow (Stomakhin et al. 2013). ``density`` ρ [kg/m³], ``youngs_modulus``
    E₀ [Pa], ``poisson_ratio`` ν, ``theta_c`` critical compression θc and
    ``theta_s`` critical stretch θs (in (0, 1)), ``hardening`` ξ. Defaults are
    the Rust core's (the paper's: 400, 1.4e5, 0.2, 2.5e-2, 7.5e-3, 10)."""

    density: float = _SNOW["density"]
    youngs_modulus: float = _SNOW["youngs_modulus"]
    poisson_ratio: float = _SNOW["poisson_ratio"]
    theta_c: float = _SNOW["theta_c"]
    theta_s: float = _SNOW["theta_s"]
    hardening: float = _SNOW["hardening"]


@dataclass
class ViscoplasticParams:
    """Viscoplastic solid: von Mises on the Hencky strain with viscous
    relaxation (Bingham). ``density`` ρ [kg/m³], ``youngs_modulus`` E [Pa],
    ``poisson_ratio`` ν, ``yield_stress`` τ_y [Pa] (the Bingham yield stress in
    simple shear: flow when √J₂ > τ_y), ``viscosity`` η [Pa·s]. Defaults are
    the Rust core's."""

    density: float = _VISCO["density"]
    youngs_modulus: float = _VISCO["youngs_modulus"]
    poisson_ratio: float = _VISCO["poisson_ratio"]
    yield_stress: float = _VISCO["yield_stress"]
    viscosity: float = _VISCO["viscosity"]


#: A parameter set of a model with a written class (a generated one is a dataclass of :func:`set_classes`).
MaterialSet = WaterParams | SandParams | ElasticParams | SnowParams | ViscoplasticParams
#: The written parameter-set classes, by the model's name.
WRITTEN: dict[str, type] = {
    "water": WaterParams,
    "sand": SandParams,
    "elastic": ElasticParams,
    "snow": SnowParams,
    "viscoplastic": ViscoplasticParams,
}


def class_name(model: str, suffix: str = "") -> str:
    """The class name of ``model`` (``"wet_foam"`` -> ``"WetFoam"`` + ``suffix``)."""
    return "".join(part.capitalize() for part in model.split("_")) + suffix


def make_set_class(model: str, rows: Sequence[Param]) -> type:
    """The parameter-set dataclass of ``model`` (``FoamParams``) made from its schema ``rows``: one
    field per row by the parameter dict's ``name``, in the rows' order, typed ``str`` for a named
    parameter and ``float`` for a number, defaulting to the row's ``default``; its docstring gives
    each row's description, unit and range."""
    described = "; ".join(f"``{p.name}`` {p.description} [{p.unit}], {p.range}" for p in rows)
    cls = make_dataclass(
        class_name(model, "Params"),
        [(p.name, str if p.choices else float, field(default=p.default)) for p in rows],
        namespace={"__doc__": f"Parameter set of the core's model ``{model}``, made from its schema: {described}. Defaults are the core's."},
    )
    cls.__module__ = __name__
    return cls


def set_classes(schema: Mapping[str, Sequence[Param]], written: Mapping[str, type] | None = None) -> dict[str, type]:
    """Each model's parameter-set class by name, in ``schema``'s order (the solver's codes): the written
    class where ``written`` (default :data:`WRITTEN`) has one, else :func:`make_set_class` of its rows."""
    written = WRITTEN if written is None else written
    return {model: written[model] if model in written else make_set_class(model, rows) for model, rows in schema.items()}


#: Each parameter-set class by the material name the parameter dict uses, for every model of the core,
#: in code order.
SET_CLASSES: dict[str, type] = set_classes(SCHEMA)
for _cls in SET_CLASSES.values():  # a made class is found by its name here (pickle, repr)
    globals().setdefault(_cls.__name__, _cls)


def set_name(cls: type) -> str | None:
    """The model whose parameter-set class is ``cls`` (:data:`SET_CLASSES`), None for another class."""
    return next((name for name, c in SET_CLASSES.items() if c is cls), None)


__all__ = [
    "SET_CLASSES",
    "WRITTEN",
    "ElasticParams",
    "MaterialSet",
    "SandParams",
    "SnowParams",
    "ViscoplasticParams",
    "WaterParams",
    "class_name",
    "make_set_class",
    "set_classes",
    "set_name",
]
