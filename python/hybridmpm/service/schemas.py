"""Request and response bodies of the API (pydantic; they make the OpenAPI schema at ``/docs``)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from enum import Enum
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model
from pydantic import Strict as StrictType

from hybridmpm.conventions import R_C, T_CTR
from hybridmpm.jsonutil import json_safe
from hybridmpm.mpm import INTEGRATORS
from hybridmpm.mpm.schema import SCHEMA, Param
from hybridmpm.scenes import DOMAINS
from hybridmpm.service.capacity import WHEN_FULL
from hybridmpm.sim import SOLVERS

#: Most points of a sketch stroke accepted over HTTP (the page simplifies to ≤ 512).
MAX_SKETCH_POINTS = 2048
#: Largest seed.
MAX_SEED = 2**31 - 1

#: A number that must be a JSON number (``true``, ``"1.5"`` refused; an integer is a number).
Number = Annotated[float, StrictType()]
#: An integer that must be a JSON integer (``true``, ``"10"``, ``10.0`` refused).
Integer = Annotated[int, StrictType()]

SceneName = Enum("SceneName", {name: name for name in sorted(DOMAINS)}, type=str)  # type: ignore[misc]
#: An MPM integrator's name (:data:`hybridmpm.mpm.INTEGRATORS`, spelled once there; the default first).
IntegratorName = Literal[INTEGRATORS]  # type: ignore[valid-type]
#: A solver kind's name (:data:`hybridmpm.sim.SOLVERS`, spelled once there; "default" first).
SolverName = Literal[SOLVERS]  # type: ignore[valid-type]
#: A boolean that must be a JSON boolean (``1``, ``"true"`` refused).
Flag = Annotated[bool, StrictType()]


class Strict(BaseModel):
    """Request bodies: unknown keys refused, no NaN or infinity, numbers
    strictly typed (:data:`Number`, :data:`Integer`)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class SceneInfo(BaseModel):
    name: str
    dim: int
    frames: int = Field(description="the scene's default rollout length [frames]")
    seeded: bool = Field(description="whether the seed changes the initial condition")
    doc: str
    solvers: list[str] = Field(
        description='the solvers a session of the scene takes; "default" (first) is the scene\'s default configuration, "realtime" its real-time mode'
    )
    default_configuration: str = Field(description='what the default solver runs for the scene (docs/hybrid.md "Defaults per scene")')
    model: bool = Field(description="whether a trained network ships for the scene (hybrid and neural solvers)")
    methods: list[str] = Field(description="the control methods a session of the scene takes (diffusion: where its controller ships)")
    default_method: str = Field(description='the control method a control without one runs (docs/control.md "Defaults")')


class CreateSession(Strict):
    scene: SceneName = Field(description="a registered scene name (GET /v1/scenes); never a path")  # type: ignore[valid-type]
    seed: Integer = Field(0, ge=0, le=MAX_SEED)
    solver: SolverName = Field(
        "default",
        description="default: the scene's default configuration, chosen by the chart (SceneInfo.default_configuration); hybrid: the paper's; "
        "realtime: MPM that keeps real time, moving between grids and integrators of the same particles (what realtime: true asks)",
    )
    r_c: Number = Field(R_C, ge=-1.0, le=1.0, description="safeguard threshold of the hybrid (higher: more MPM)")
    n_grid: Integer | None = Field(
        None,
        ge=16,
        le=4096,
        description="solver mpm: run on a coarser grid of the scene's domain (the same blocks, obstacles and wall faces; "
        "at most the scene's own grid); null: the scene's grid",
    )
    integrator: IntegratorName | None = Field(
        None,
        description="solver mpm: how a frame advances (explicit MLS-MPM substeps, or projection: incompressible water at the flow's pace; "
        "water scenes without obstacles or bodies only); null: the scene's",
    )
    realtime: Flag | None = Field(
        None,
        description="true: run in real-time mode (solver realtime: the most accurate grid and integrator whose frame keeps real time on the "
        "server, changed as its pace changes); with solver default or realtime only, no n_grid or integrator; false: not; "
        "null: the server's default (serve --realtime makes a session of the default solver real-time)",
    )
    when_full: Literal[WHEN_FULL] = Field(  # type: ignore[valid-type]
        WHEN_FULL[0],
        description="a real-time session on a server whose real time is full (the playing real-time sessions fill its cores): refuse, a 503 "
        "saying how many play and at what cost; coarser, start at the most accurate configuration that fits (a 503 when none does)",
    )


class PlanInfo(BaseModel):
    """Where the controller plans the fluid's centroid over the controlled horizon."""

    method: str
    frames: int = Field(description="the control horizon T_ctr [frames]")
    stride: int = Field(description="control frames between consecutive points of centroid_path")
    centroid_path: list[list[float]] = Field(
        description="the planned centroid of the fluid [m] at control frames 0, stride, 2·stride, …, frames (the last point is where "
        "the plan ends: the arrow's tip relative to the start centroid, or the oval's centre); D coordinates (in 3D z as planned)"
    )
    target: list[float] = Field(description="the centroid the sketch asks for [m], x–y (an arrow: start centroid + the arrow; an oval: its centre)")


class RunningControl(BaseModel):
    """A control running on a session: what its stream's ``control running`` event says, with the plan once made."""

    status: Literal["running"] = "running"
    id: str
    method: str
    frames: int = Field(description="the control horizon T_ctr [frames]")
    start_frame: int = Field(description="the session's frame when the control started")
    sketch: dict[str, Any] | None = Field(description="the sketch it follows (the request's sketch JSON, domain coordinates, y up); null for none")
    plan: PlanInfo | None = Field(None, description="the plan's centroid path once the controller has made it; null before")


class RealtimeInfo(BaseModel):
    """What a real-time session is doing (:meth:`hybridmpm.sim.RealtimeSimulator.realtime_info`; its stream's
    ``realtime`` events carry the same keys)."""

    model_config = ConfigDict(extra="allow")

    rung: str = Field(description="the configuration in use, g{n_grid}-{integrator} (e.g. g96-explicit): one of ladder")
    label: str = Field(description='the rung for people, e.g. "MPM 96² explicit"')
    frame_ms: float | None = Field(description="its measured wall time per frame [ms] (a running average); null before it was timed")
    budget_ms: float = Field(description="a frame's wall-time budget [ms]: the simulated time a frame covers, less a margin for the rest of the host")
    realtime_factor: float | None = Field(
        description="simulated seconds a wall second of stepping covers on this rung (1.0: real time; above: faster); null before it was timed"
    )
    changes: int = Field(description="changes of rung so far")
    ladder: list[str] = Field(description="the rungs it moves between, most accurate first")
    share: float = Field(1.0, description="the share of its threads' time it may spend, in (0, 1]: below 1 while real time fills its machine (Ray: node)")


class SessionInfo(BaseModel):
    id: str = Field(description="unguessable session id (192 bits, 32 URL-safe characters); the session's only credential")
    scene: str
    seed: int
    solver: str
    r_c: float
    dim: int
    num_fluid: int
    num_particles: int = Field(description="fluid + boundary particles (the obstacles', not simulated; the rows of every positions array)")
    particle_type: list[int] = Field(description="GNS type per particle: 5 water, 6 sand, 3 boundary")
    bounds: list[list[float]] = Field(description="[[lo...], [hi...]] of the domain [m]")
    dt_frame: float
    r_t: int = Field(description="frames per coarse step of the solver")
    frame: int
    viewers: int = Field(0, description="WebSocket clients watching the session")
    stream: str = Field(description="WebSocket path of the frame stream")
    saved_frame: int | None = Field(None, description="with a store (serve --store): the frame of the session's last save; null without one")
    restored_from_frame: int | None = Field(
        None, description="the frame the session resumed from when a restarted server restored it from its store; null if it was not restored"
    )
    n_grid: int | None = Field(None, description="grid cells per dimension of the scene's MPM grid")
    integrator: str = Field(
        description="what the session's MPM steps with (hybridmpm.mpm.INTEGRATORS: explicit MLS-MPM substeps, or the incompressible "
        "projection); a hybrid or neural session's MPM part runs its scene's"
    )
    realtime: RealtimeInfo | None = Field(None, description="a real-time session (solver realtime): what real-time mode is doing; null for any other")
    wall_thickness: float = Field(0.0, description="thickness of the domain's walls [m]: the fluid stays within [t, 1 - t] on every axis")
    obstacles: list[dict[str, Any]] = Field(
        default_factory=list,
        description="the scene's static obstacles (MPM colliders): {shape: 'box', center, half_extents, angle_deg (2D) or rotation "
        "(3D, 3×3, world = center + rotation · local)} or {shape: 'sphere', center, radius} [m], with their wall condition and friction",
    )
    obstacle_centers: list[list[float]] = Field(
        default_factory=list, description="each obstacle's centre now [m] (moved by PUT .../obstacles/{index} or its scene's path)"
    )
    bodies: list[dict[str, Any]] = Field(
        default_factory=list,
        description="the session's rigid bodies (docs/bodies.md): {shape, half_extents or radius, mass [kg; per unit depth in 2D], center, "
        "rotation (D×D), velocity, angular_velocity} at its current frame",
    )
    recorded_frames: int = Field(0, description="coarse steps of the session's recent trajectory held for download (GET .../trajectory)")
    control: RunningControl | None = Field(
        None, description="the control running on the session now (what a viewer that joins meanwhile shows); null when none runs"
    )


class StepRequest(Strict):
    frames: Integer = Field(1, ge=1, le=100, description="frames to advance (whole coarse steps: ceil(frames / r_t))")


class ObstacleMove(Strict):
    center: list[Number] = Field(min_length=2, max_length=3, description="where the obstacle's centre goes over the next step [m] (D numbers in [0, 1])")
    velocity: list[Number] | None = Field(
        None, min_length=2, max_length=3, description="the velocity it pushes the fluid with [m/s]; null: the move over the step's duration"
    )


#: The most parameters a pour body's ``params`` may give (every model has fewer).
MAX_POUR_PARAMS = 16


class _BlockPlace(Strict):
    """Where a block goes, what it is, and its parameters in ``params``; :data:`BlockPour` adds each
    parameter as a flat key too."""

    material: str = Field(max_length=32, description=f"a model ({', '.join(SCHEMA)}) or a preset (jello, mud, ...)")
    lo: list[Number] = Field(min_length=2, max_length=3, description="one corner [m], inside the walls' faces")
    hi: list[Number] = Field(min_length=2, max_length=3, description="the opposite corner [m]")
    velocity: list[Number] | None = Field(None, min_length=2, max_length=3, description="initial velocity [m/s] (default at rest)")
    params: dict[Annotated[str, Field(max_length=32)], Number | Annotated[str, Field(max_length=16)]] | None = Field(
        None,
        max_length=MAX_POUR_PARAMS,
        description="the material's parameters by the user's key ({'E': 5e4, 'nu': 0.3}; each model's keys, units, ranges and defaults "
        "are GET /v1/materials', the flat keys' descriptions and docs/materials.md's tables): each overrides the model's table in the scene or the "
        "preset's value; a key the chosen model lacks, or one also given flat, is a 422 naming it",
    )


def _flat_field(schema: Mapping[str, Sequence[Param]], key: str) -> Any:
    """A flat pour key (``E``) as a pydantic field, described from every model's row of it in ``schema``."""
    rows: dict[tuple[str, str, str], list[str]] = {}
    for model, params in schema.items():
        for p in params:
            if p.key == key:
                rows.setdefault((p.description, p.unit, p.range), []).append(model)
    text = "; ".join(f"{', '.join(models)}: {desc} [{unit}], {rng}" for (desc, unit, rng), models in rows.items())
    choices = next(p.choices for params in schema.values() for p in params if p.key == key)
    kind: Any = Annotated[str, Field(max_length=16)] if choices else Number
    return (kind | None, Field(None, description=text))


def block_pour_model(schema: Mapping[str, Sequence[Param]]) -> type[_BlockPlace]:
    """The pour body of ``schema`` (``{model: rows}``, :data:`hybridmpm.mpm.schema.SCHEMA` for
    :data:`BlockPour`): :class:`_BlockPlace` with every model's parameters by the user's key as flat keys,
    each an optional number (a string for a named parameter), in the schema's order."""
    flat = list(dict.fromkeys(p.key for params in schema.values() for p in params))
    model: type[_BlockPlace] = create_model(
        "BlockPour",
        __base__=_BlockPlace,
        __doc__="A block poured into a session: a scene file's block (docs/materials.md), its parameters in params or flat.",
        **{k: _flat_field(schema, k) for k in flat},
    )
    return model


if TYPE_CHECKING:
    BlockPour = _BlockPlace
else:
    #: A block poured into a session: a scene file's block (docs/materials.md): ``material``, ``lo``, ``hi``,
    #: ``velocity``, and the material's parameters in ``params`` or as flat keys (the page sends the flat
    #: form); the flat keys are every model's parameters by the user's key (:data:`hybridmpm.mpm.schema.SCHEMA`).
    BlockPour = block_pour_model(SCHEMA)


class MaterialParam(BaseModel):
    """One parameter of a model, a row of the core's one schema (:class:`hybridmpm.mpm.schema.Param`)."""

    name: str = Field(description="its key in the solver's parameter set (youngs_modulus)")
    key: str = Field(description="the user's key, which a pour's params and flat keys and a scene file's block take (E)")
    unit: str = Field(description="SI unit; '-' dimensionless")
    lower: float | None = Field(description="the lower bound; null: none (and for a named parameter)")
    lower_inclusive: bool | None = Field(description="whether lower is allowed; null where there is no lower bound")
    upper: float | None = Field(description="the upper bound; null: none")
    upper_inclusive: bool | None = Field(description="whether upper is allowed; null where there is no upper bound")
    choices: list[str] = Field(description="the names a named parameter takes; empty for a number")
    range: str = Field(description="the range in the words a refusal uses ('in [0, 0.5)')")
    default: float | str = Field(description="the core's default")
    description: str
    source: str = Field(description="where the model or the value comes from")


class MaterialPreset(BaseModel):
    model: str = Field(description="the model the preset is a parameter set of")
    params: dict[str, float | str] = Field(description="every parameter of the model by the user's key")
    source: str = Field(description="where its numbers come from")


class MaterialsInfo(BaseModel):
    models: dict[str, list[MaterialParam]] = Field(description="each model's parameters, in the order of the core's parameter set")
    presets: dict[str, MaterialPreset] = Field(description="the presets a pour's material names (hybridmpm.materials.PRESETS)")


class BlockPoured(BaseModel):
    added: int = Field(description="particles added")
    num_particles: int = Field(description="the session's particles now (with boundary particles)")
    frame: int = Field(description="the session's frame when the block was poured")


#: Longest JSON text of a float64 at full precision [characters]: its shortest round-trip form
#: (Python's ``repr``, JavaScript's ``String``) is at most 24 characters, ``-2.2250738585072014e-308``.
MAX_NUMBER_CHARS = 24
#: Most bytes one point ``[x, y, z], `` of ``BodyAdd.vertices`` takes at full precision (``json.dumps``'
#: separators ``", "``; ``JSON.stringify``'s take 4 fewer).
VERTEX_JSON_BYTES = 3 * MAX_NUMBER_CHARS + 8
#: Most points a mesh body added over HTTP may give (``BodyAdd.vertices``): so many that they fit in the
#: JSON body cap (``ServiceConfig.max_json_bytes``, 64 KiB by default) at full float64 precision, so that a
#: request with one point too many is answered 422 naming ``vertices``, never 413. 512 points take at most
#: 512 × 80 B = 40 KiB, which leaves 24 KiB of the default cap to the other fields and whitespace (enough
#: for ``json.dumps(..., indent=2)``). A larger hull comes in a scene file (``[[bodies]]`` ``path``).
MAX_BODY_VERTICES = 512


class BodyAdd(Strict):
    """A rigid body added to a session: a scene file's ``[[bodies]]`` table (docs/bodies.md). A mesh body
    (3D) comes as its points inline (``vertices``, at most :data:`MAX_BODY_VERTICES`), never as a path: a
    request names no file on the server's disk."""

    shape: Literal["box", "sphere", "circle", "capsule", "mesh"] = Field(
        description="box (half_extents), sphere / circle (radius), capsule (radius, half_height) or, in 3D, mesh (vertices: the body is their convex hull)"
    )
    center: list[Number] = Field(min_length=2, max_length=3, description="its centre of mass [m], inside the walls (a mesh: where its points' origin goes)")
    half_extents: list[Number] | None = Field(None, min_length=2, max_length=3, description="box: half its size along its axes [m], at least 1 cell")
    radius: Number | None = Field(None, description="sphere / circle / capsule: its radius [m], at least 1 cell")
    half_height: Number | None = Field(None, description="capsule: half the length of its segment along the body's y axis [m], at least 1 cell")
    vertices: list[tuple[Number, Number, Number]] | None = Field(
        None,
        min_length=4,
        max_length=MAX_BODY_VERTICES,
        description="mesh (3D): its points [[x, y, z], ...] [m]; the body is their convex hull, at least 2 cells thick",
    )
    angle_deg: Number | None = Field(None, description="2D: its rotation, counter-clockwise [deg] (default 0)")
    rotation: list[list[Number]] | None = Field(None, min_length=2, max_length=3, description="its rotation, D×D (columns: the body's axes)")
    density: Number | None = Field(None, description="[kg/m^3], > 0; or mass")
    mass: Number | None = Field(None, description="[kg; per unit depth in 2D], > 0; or density")
    velocity: list[Number] | None = Field(None, min_length=2, max_length=3, description="[m/s] (default at rest)")
    angular_velocity: Number | list[Number] | None = Field(None, description="[rad/s]: one number in 2D, three in 3D (default 0)")
    friction: Number | None = Field(None, description="Coulomb friction against the fluid, >= 0 (default 0)")


class BodyAdded(BaseModel):
    index: int = Field(description="the body's index (its place in the session's bodies)")
    num_bodies: int = Field(description="the session's bodies now")
    frame: int = Field(description="the session's frame when the body was added or removed")


class ObstacleMoved(BaseModel):
    index: int
    center: list[float]
    frame: int = Field(description="the session's frame when the move was accepted (the obstacle arrives at the end of the next step)")


class StepFrame(BaseModel):
    step: int
    frame: int
    time: float
    solver: str
    seconds: float = Field(description="wall time of the step [s]")
    controlled: bool
    positions: list[list[float]]
    bodies: list[dict[str, Any]] | None = Field(
        None, description="a session with rigid bodies: each body's {center, rotation (D×D)} at the frame's end; absent without bodies"
    )


class StepResponse(BaseModel):
    frames: list[StepFrame]
    failure: str | None = None
    latency_ms: float = Field(description="wall time of the whole request's simulation [ms]")


class SketchIn(Strict):
    kind: Literal["arrow", "oval"]
    points: list[tuple[Number, Number]] = Field(min_length=2, max_length=MAX_SKETCH_POINTS, description="[[x, y], ...] domain coordinates, y up")
    t: list[Number] | None = Field(None, max_length=MAX_SKETCH_POINTS)
    width: list[Number] | None = Field(None, max_length=MAX_SKETCH_POINTS)


class ControlRequest(Strict):
    sketch: SketchIn | None = None
    sketch_png: str | None = Field(
        None, max_length=60_000, description="the sketch as a PNG image (base64), the domain [0, 1]² filling it with y up; instead of `sketch`"
    )
    method: Literal["constant", "pd", "mpc", "none", "diffusion"] | None = Field(
        None, description="the control method (SceneInfo.methods); null: the scene's default (SceneInfo.default_method)"
    )
    frames: Integer = Field(T_CTR, ge=1, le=1000, description="control horizon T_ctr [frames]")


class ControlResponse(BaseModel):
    id: str
    method: str
    frames: int
    shape: list[int] = Field(description="[T_ctr + 1, N + B, D] of the trajectory")
    start_frame: int
    end_frame: int
    metrics: dict[str, Any]
    sketch: dict[str, Any] | None
    sketch_png: str | None = Field(description="the rendered sketch the controller saw (PNG, base64)")
    first_frame_ms: float = Field(description="request received → first controlled frame [ms]")
    total_ms: float
    trajectory: str = Field(description="path of the trajectory (npz, or float32 with Accept: application/octet-stream)")
    plan: PlanInfo | None = Field(None, description="the plan's centroid path (null for method none or no sketch)")


class Health(BaseModel):
    status: str
    sessions: int
    max_sessions: int
    memory_used: int = Field(description="bytes of the memory budget held by sessions, kept controls and requests in flight")
    memory_budget: int = Field(description="the process's memory budget [bytes]")
    version: str
    solvers: list[str] = Field(description="the solver kinds a session may ask for (hybridmpm.sim.SOLVERS; a scene's own in GET /v1/scenes)")
    realtime_default: bool = Field(description="whether a session created without realtime runs in real-time mode (serve --realtime)")


def clean(obj: Any) -> Any:
    """``obj`` as strict JSON values (:func:`hybridmpm.jsonutil.json_safe`)."""
    return json_safe(obj)
