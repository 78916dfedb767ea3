"""Materials as users pour them: the core's constitutive models in the field's
standard terms, and presets named as artists know them (docs/materials.md).

Each class is one model with its parameters in SI units, named as a scene
file's block names them (``E``, ``nu``, ``density``, ...); their ranges,
defaults and these user keys are the core's one schema
(:data:`hybridmpm.mpm.schema.SCHEMA`), which each class's fields follow in
name and order (tests/test_material_schema.py). Water, sand, the elastic
solid, snow and the viscoplastic solid have written classes; every other
model of the core gets one made from its schema (:func:`material_classes`),
in :data:`MODELS` beside them. ``to_params()``
gives the solver's parameter set (:mod:`hybridmpm.mpm.params`), ``code`` the
solver material code (:data:`~hybridmpm.conventions.MATERIALS`). A scene
file's block takes a material by name or by preset
(``material = "elastic"``, ``material = "jello"``) and overrides any key::

    [[blocks]]
    material = "jello"
    E = 5.0e4
    lo = [0.4, 0.5]
    hi = [0.6, 0.7]

>>> import hybridmpm as hm
>>> hm.materials.Elastic(E=1e5, nu=0.3).code
2
>>> hm.materials.PRESETS["snow"].theta_c
0.025
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, make_dataclass, replace
from typing import Any, ClassVar

import numpy as np

from hybridmpm.conventions import (
    GNS_TYPE_OF_MATERIAL,
    LEARNED_MATERIALS,
    MATERIAL_ELASTIC,
    MATERIAL_SAND,
    MATERIAL_SNOW,
    MATERIAL_VISCOPLASTIC,
    MATERIAL_WATER,
    MATERIALS,
)
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.schema import SCHEMA, Param, check_set
from hybridmpm.mpm.sets import SET_CLASSES, class_name

#: Each model's defaults by the user's key (``E``, ``nu``, ...): the core's (``_core.material_schema()``).
_D: dict[str, dict[str, Any]] = {model: {p.key: p.default for p in params} for model, params in SCHEMA.items()}


@dataclass(frozen=True)
class _Material(abc.ABC):
    """A material of one model. Its fields (each subclass's own) are the model's parameters by the user's
    key, in the core's order (:data:`hybridmpm.mpm.schema.SCHEMA`, which gives their ranges and defaults
    too); every model has a ``density`` ρ [kg/m³]."""

    name: ClassVar[str]
    code: ClassVar[int]

    def validate(self, where: str = "") -> None:
        """Check every parameter against the core's range in float64 and in float32; raises
        :class:`InvalidInputError` naming the user's key with the value given (``where`` is prepended,
        e.g. ``blocks[2].``)."""
        check_set(where, self.name, asdict(self), by_key=True)

    def to_params(self) -> Any:
        """The core's parameter set of this material (:mod:`hybridmpm.mpm.params`, e.g. ``ElasticParams``)."""
        return SET_CLASSES[self.name](**{p.name: getattr(self, p.key) for p in SCHEMA[self.name]})

    @classmethod
    def from_params(cls, ps: Any) -> Any:
        """The material of the core's parameter set ``ps`` (the inverse of :meth:`to_params`)."""
        return cls(**{p.key: getattr(ps, p.name) for p in SCHEMA[cls.name]})


@dataclass(frozen=True)
class Water(_Material):
    """Weakly compressible water (Hu et al. 2018, mpm88): pressure
    ``K(1 − J)``, Newtonian viscosity. ``density`` ρ [kg/m³],
    ``bulk_modulus`` K [Pa] (sound speed √(K/ρ)), ``viscosity`` η [Pa·s]."""

    name: ClassVar[str] = "water"
    code: ClassVar[int] = MATERIAL_WATER
    density: float = _D["water"]["density"]
    bulk_modulus: float = _D["water"]["bulk_modulus"]
    viscosity: float = _D["water"]["viscosity"]


@dataclass(frozen=True)
class Sand(_Material):
    """Drucker–Prager sand on the Hencky strain (Klár et al. 2016).
    ``E`` [Pa], ``nu`` [-], ``friction_angle_deg`` φ [°], ``cohesion`` c [Pa],
    ``density`` ρ [kg/m³]."""

    name: ClassVar[str] = "sand"
    code: ClassVar[int] = MATERIAL_SAND
    density: float = _D["sand"]["density"]
    E: float = _D["sand"]["E"]
    nu: float = _D["sand"]["nu"]
    friction_angle_deg: float = _D["sand"]["friction_angle_deg"]
    cohesion: float = _D["sand"]["cohesion"]


@dataclass(frozen=True)
class Elastic(_Material):
    """Elastic solid ("jelly"). ``E`` Young's modulus [Pa], ``nu`` Poisson's
    ratio, ``density`` ρ [kg/m³], ``model``: ``"corotated"``
    (fixed-corotated, Stomakhin et al. 2012: τ = 2μ(F − R)Fᵀ + λJ(J − 1)I) or
    ``"neohookean"`` (τ = μ(FFᵀ − I) + λ ln J·I)."""

    name: ClassVar[str] = "elastic"
    code: ClassVar[int] = MATERIAL_ELASTIC
    density: float = _D["elastic"]["density"]
    E: float = _D["elastic"]["E"]
    nu: float = _D["elastic"]["nu"]
    model: str = _D["elastic"]["model"]


@dataclass(frozen=True)
class Snow(_Material):
    """Snow (Stomakhin et al. 2013, "A material point method for snow
    simulation"): fixed-corotated elasticity on F_E, singular values clamped
    to [1 − θc, 1 + θs], Lamé parameters hardened by e^{ξ(1 − J_P)}.
    ``E`` E₀ [Pa], ``nu`` [-], ``theta_c`` θc and ``theta_s`` θs,
    ``hardening`` ξ [-], ``density`` ρ [kg/m³]. Defaults: the paper's."""

    name: ClassVar[str] = "snow"
    code: ClassVar[int] = MATERIAL_SNOW
    density: float = _D["snow"]["density"]
    E: float = _D["snow"]["E"]
    nu: float = _D["snow"]["nu"]
    theta_c: float = _D["snow"]["theta_c"]
    theta_s: float = _D["snow"]["theta_s"]
    hardening: float = _D["snow"]["hardening"]


@dataclass(frozen=True)
class Viscoplastic(_Material):
    """Viscoplastic solid (Bingham mud; plasticine at zero viscosity): von
    Mises plasticity on the Hencky strain with viscous relaxation.
    ``yield_stress`` τ_y [Pa] is the Bingham yield stress in simple shear
    (flow when √J₂ > τ_y), ``viscosity`` η [Pa·s] the plastic viscosity (in
    steady shear at rate γ̇ the shear stress is τ_y + η·γ̇), ``E`` [Pa] and
    ``nu`` the elastic part, ``density`` ρ [kg/m³]."""

    name: ClassVar[str] = "viscoplastic"
    code: ClassVar[int] = MATERIAL_VISCOPLASTIC
    density: float = _D["viscoplastic"]["density"]
    E: float = _D["viscoplastic"]["E"]
    nu: float = _D["viscoplastic"]["nu"]
    yield_stress: float = _D["viscoplastic"]["yield_stress"]
    viscosity: float = _D["viscoplastic"]["viscosity"]


#: A material of any model of the core: a written class (:class:`Water`, :class:`Sand`, :class:`Elastic`,
#: :class:`Snow`, :class:`Viscoplastic`) or one made from the schema (:func:`material_classes`).
Material = _Material
#: The written material classes, by the model's name.
WRITTEN: dict[str, type[_Material]] = {c.name: c for c in (Water, Sand, Elastic, Snow, Viscoplastic)}


def make_material_class(model: str, code: int, rows: Sequence[Param]) -> type[_Material]:
    """The material class of ``model`` (``"foam"`` -> ``Foam``) made from its schema ``rows``: a frozen
    dataclass subclass of the materials' base with ``name`` ``model`` and ``code`` ``code`` (the solver's),
    one field per row by the user's ``key``, in the rows' order, typed ``str`` for a named parameter and
    ``float`` for a number, defaulting to the row's ``default``; its docstring gives each row's
    description, unit and range. Its :meth:`~_Material.validate`, :meth:`~_Material.to_params` and
    :meth:`~_Material.from_params` read the model's rows of :data:`~hybridmpm.mpm.schema.SCHEMA` and its
    set class of :data:`~hybridmpm.mpm.sets.SET_CLASSES` (the core's, where ``model`` is one of its models)."""
    described = "; ".join(f"``{p.key}`` {p.description} [{p.unit}], {p.range}" for p in rows)
    cls = make_dataclass(
        class_name(model),
        [(p.key, str if p.choices else float, field(default=p.default)) for p in rows],
        bases=(_Material,),
        frozen=True,
        namespace={"name": model, "code": code, "__doc__": f"The core's model ``{model}``, made from its schema: {described}."},
    )
    cls.__module__ = __name__
    return cls


def material_classes(
    schema: Mapping[str, Sequence[Param]], codes: Mapping[str, int], written: Mapping[str, type[_Material]] | None = None
) -> dict[str, type[_Material]]:
    """Each model's material class by the name a scene file's block gives, in ``schema``'s order: the
    written class where ``written`` (default :data:`WRITTEN`) has one, else :func:`make_material_class`
    of its rows and its solver code in ``codes`` (``{name: code}``; a model ``codes`` lacks raises
    ``KeyError``)."""
    written = WRITTEN if written is None else written
    return {model: written[model] if model in written else make_material_class(model, codes[model], rows) for model, rows in schema.items()}


#: Each model's class by the name a scene file's block gives: one per model of the core, in code order.
MODELS: dict[str, type[_Material]] = material_classes(SCHEMA, MATERIALS)
for _cls in MODELS.values():  # a made class is found by its name here (pickle, repr)
    globals().setdefault(_cls.__name__, _cls)

#: Presets named as artists know them: each a parameter set of one model,
#: with its source in :data:`PRESET_SOURCES` (orders of magnitude where the
#: material varies; docs/materials.md).
PRESETS: dict[str, Material] = {
    "jello": Elastic(density=1050.0, E=2.0e4, nu=0.45),
    "rubber": Elastic(density=1100.0, E=1.0e6, nu=0.45, model="neohookean"),
    "snow": Snow(),
    "mud": Viscoplastic(density=1800.0, E=1.0e6, nu=0.3, yield_stress=100.0, viscosity=10.0),
    "plasticine": Viscoplastic(density=1800.0, E=2.0e6, nu=0.3, yield_stress=2.0e4, viscosity=0.0),
    "honey": Water(density=1420.0, viscosity=10.0),
    "soil": Sand(density=1600.0, E=1.0e6, nu=0.3, friction_angle_deg=32.0, cohesion=500.0),
}
#: Where each preset's numbers come from.
PRESET_SOURCES: dict[str, str] = {
    "jello": "gelatin gels: E of order 10 kPa, density near water's, nearly incompressible (ν held at 0.45 for the explicit step)",
    "rubber": "soft rubber: E of order 1 MPa, ν near 0.5 (held at 0.45), neo-Hookean (the usual rubber energy)",
    "snow": "Stomakhin et al. 2013, Table 2 (E₀ = 1.4e5 Pa, ν = 0.2, θc = 2.5e-2, θs = 7.5e-3, ξ = 10, ρ = 400)",
    "mud": "mudflow rheology (Coussot 1997, 'Mudflow rheology and dynamics'): Bingham yield stresses 10-1000 Pa, viscosities 1-100 Pa·s",
    "plasticine": "modelling clay: flow stress of order 10 kPa in shear, no rate dependence (η = 0)",
    "honey": "honey at 20 °C: a Newtonian liquid of viscosity of order 10 Pa·s and density 1420 kg/m³",
    "soil": "loose silty sand / soil: friction angle about 30°, small cohesion (Terzaghi-style textbook ranges)",
}


def scene_bases(params: Any) -> dict[str, Material]:
    """Each model's base material in a scene whose solver parameters are ``params``
    (:class:`~hybridmpm.mpm.MpmParams`): the scene's own table of the model
    (a scene file's ``[water]`` and ``[sand]``; ``MpmParams.water``, ``.sand``,
    ``.elastic``, ``.snow``, ``.viscoplastic``, any further model's in ``MpmParams.tables``:
    :meth:`~hybridmpm.mpm.MpmParams.table`), as a block naming the model starts from."""
    return {name: cls.from_params(params.table(name)) for name, cls in MODELS.items()}


def _base(name: Any, where: str, bases: dict[str, Material] | None) -> Material:
    """The material a block's keys override: a preset's own parameters, or the model's
    table in the scene (``bases``; the model's defaults without one)."""
    if isinstance(name, str) and name in PRESETS:
        return PRESETS[name]
    if isinstance(name, str) and name in MODELS:
        return bases[name] if bases is not None else MODELS[name]()
    raise InvalidInputError(f"{where}.material: must be one of {sorted(MODELS)} or a preset {sorted(PRESETS)}, got {name!r}", f"{where}.material")


def material_from_block(name: Any, keys: dict[str, Any], where: str, bases: dict[str, Material] | None = None) -> Material:
    """The material of a scene block: ``name`` a model (``"elastic"``, any of
    :data:`MODELS`) or a preset (``"jello"``), ``keys`` the block's overrides
    (``E``, ``nu``, ``density``, ``model``, ``theta_c``, ``theta_s``,
    ``hardening``, ``yield_stress``, ``viscosity``, ...: the user's keys of the
    model's schema, those of the model only). ``where`` names
    the block (``blocks[2]``).

    The rule for scene-level and block-level parameters: a block naming a
    model starts from the scene's table of that model (``bases``, from
    :func:`scene_bases`: a scene file's ``[water]`` or ``[sand]``; the model's
    defaults when ``bases`` is None); a block naming a preset starts from the
    preset; the block's own keys override either. Raises
    :class:`InvalidInputError` naming the field."""
    base = _base(name, where, bases)
    allowed = {f.name for f in fields(base)}
    for k in keys:
        if k not in allowed:
            raise InvalidInputError(f"{where}.{k}: not a parameter of {base.name} (allowed: {', '.join(sorted(allowed))})", f"{where}.{k}")
    m = replace(base, **keys)
    m.validate(where + ".")
    return m


def block_keys(m: Material, name: str, bases: dict[str, Material] | None = None) -> dict[str, Any]:
    """The keys a scene block writes for material ``m`` given as ``name`` (a
    model or preset): the values that differ from its base (:func:`material_from_block`'s rule)."""
    base = _base(name, "block", bases)
    return {k: v for k, v in asdict(m).items() if asdict(base)[k] != v}


def refuse_untrained(material: Any, who: str, *, gns: bool = False) -> None:
    """Raise :class:`InvalidInputError` (field ``material``) naming the first
    material of ``material`` (solver codes [N]; GNS particle types with
    ``gns``) that the learned ``who`` was not trained on
    (:data:`~hybridmpm.conventions.LEARNED_MATERIALS`); PD control and MPM run
    every material."""
    codes = np.unique(np.asarray(material, np.int64)).tolist()
    names = {code: name for name, code in MATERIALS.items()}
    if gns:
        names = {GNS_TYPE_OF_MATERIAL[code]: name for code, name in names.items()}
    for c in codes:
        name = names.get(int(c))
        if name is not None and name not in LEARNED_MATERIALS:
            raise InvalidInputError(
                f"material: the {who} was trained on {' and '.join(LEARNED_MATERIALS)} only, and this scene holds {name}; "
                "run it with the mpm solver (and PD control)",
                "material",
            )


__all__ = [
    "MODELS",
    "PRESETS",
    "WRITTEN",
    "PRESET_SOURCES",
    "Elastic",
    "Material",
    "Sand",
    "Snow",
    "Viscoplastic",
    "Water",
    "block_keys",
    "make_material_class",
    "material_classes",
    "material_from_block",
    "refuse_untrained",
    "scene_bases",
]
