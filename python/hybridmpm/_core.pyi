"""Type stubs of the native module ``hybridmpm._core`` (checked by mypy.stubtest)."""

from typing import Any, final

import numpy as np
import numpy.typing as npt

__all__ = ["__version__", "BODY_STATE_LEN", "CONNECTIVITY_RADIUS", "INTEGRATORS", "MATERIAL_CODES", "MAX_BODIES", "MAX_BODY_DENSITY", "MAX_BODY_SPEED", "MAX_HULL_POINTS", "MIN_BODY_DENSITY", "MpmSolver", "PROJECT_DEPTH_CELLS", "SOLID_PROJECT_DEPTH_CELLS", "bodies_overlap", "body_hull", "body_sdf", "check_body", "default_collider", "default_params", "grid_advect", "grid_g2p", "grid_mass", "grid_p2g", "kernel_density", "material_schema", "radius_graph", "relax_density", "relax_then_graph", "surface_p2g"]

__version__: str
CONNECTIVITY_RADIUS: float
INTEGRATORS: tuple[str, ...]
MATERIAL_CODES: dict[str, int]
MAX_BODIES: int
MAX_HULL_POINTS: int
MIN_BODY_DENSITY: float
MAX_BODY_DENSITY: float
MAX_BODY_SPEED: float
BODY_STATE_LEN: int
PROJECT_DEPTH_CELLS: float
SOLID_PROJECT_DEPTH_CELLS: float

@final
class MpmSolver:
    def __new__(cls, params: dict[str, Any], memory_budget: int | None = None) -> MpmSolver: ...
    @property
    def dim(self) -> int: ...
    @property
    def n_grid(self) -> int: ...
    @property
    def dx(self) -> float: ...
    @property
    def bytes_per_particle(self) -> int: ...
    @property
    def memory_budget(self) -> int | None: ...
    @property
    def num_particles(self) -> int: ...
    @property
    def time(self) -> float: ...
    @property
    def mode_runs(self) -> tuple[int, int]: ...
    @property
    def isa(self) -> str: ...
    def set_isa(self, name: str) -> None: ...
    @property
    def frame(self) -> int: ...
    @property
    def domain_bounds(self) -> tuple[float, float]: ...
    def add_particles(
        self,
        positions: npt.NDArray[np.float32],
        material: int | npt.ArrayLike,
        *,
        velocities: npt.NDArray[np.float32] | None = None,
        masses: npt.NDArray[np.float32] | None = None,
        volumes: npt.NDArray[np.float32] | None = None,
        material_set: int | npt.ArrayLike | None = None,
    ) -> int: ...
    def add_parameter_set(self, set: dict[str, Any]) -> int: ...
    def remove_particles(self, mask: npt.ArrayLike) -> int: ...
    def get(self, field: str) -> npt.NDArray[Any]: ...
    def set(self, field: str, value: npt.ArrayLike) -> None: ...
    def substeps_for(self, dt_frame: float = 0.0025) -> int: ...
    def step_frame(self, dt_frame: float = 0.0025) -> dict[str, float]: ...
    @property
    def collider_positions(self) -> npt.NDArray[np.float32]: ...
    @property
    def collider_moves(self) -> list[tuple[int, list[float], list[float] | None]]: ...
    def place_collider(self, index: int, position: npt.NDArray[np.float32]) -> None: ...
    def move_collider(self, index: int, position: npt.NDArray[np.float32], velocity: npt.NDArray[np.float32] | None = None) -> None: ...
    def bodies(self) -> dict[str, npt.NDArray[Any]]: ...
    def add_body(self, body: dict[str, Any]) -> int: ...
    def remove_body(self, index: int) -> None: ...
    def set_body_state(self, index: int, state: npt.NDArray[np.float32]) -> None: ...
    def check_body_state(self, index: int, state: npt.NDArray[np.float32]) -> None: ...
    def set_body_force(self, index: int, force: list[float]) -> None: ...
    def checkpoint(self) -> bytes: ...
    def restore(self, blob: bytes) -> None: ...

def default_params(dim: int) -> dict[str, Any]: ...
def default_collider() -> dict[str, Any]: ...
def material_schema() -> dict[str, list[dict[str, Any]]]: ...
def check_body(body: dict[str, Any], dim: int, n_grid: int, wall_cells: int, index: int) -> float: ...
def body_hull(points: list[list[float]], field: str) -> dict[str, Any]: ...
def bodies_overlap(a: dict[str, Any], b: dict[str, Any], dim: int, ia: int, ib: int) -> bool: ...
def body_sdf(
    body: dict[str, Any],
    points: npt.NDArray[np.float64],
    center: list[float] | None = None,
    rotation: list[list[float]] | None = None,
) -> npt.NDArray[np.float64]: ...
def grid_mass(
    positions: npt.NDArray[np.float32],
    n_grid: int,
    masses: npt.NDArray[np.float32] | None = None,
    *,
    memory_budget: int | None = None,
) -> npt.NDArray[np.float32]: ...
def grid_p2g(
    positions: npt.NDArray[np.float32],
    values: npt.NDArray[np.float32],
    origin: list[float],
    spacing: list[float],
    nodes: int,
) -> npt.NDArray[np.float32]: ...
def surface_p2g(
    positions: npt.NDArray[np.float64],
    values: npt.NDArray[np.float64],
    spacing: float,
    origin: list[int],
    shape: list[int],
    weight_scale: float,
) -> npt.NDArray[np.float64]: ...
def grid_g2p(
    field: npt.NDArray[np.float32],
    positions: npt.NDArray[np.float32],
    origin: list[float],
    spacing: list[float],
    nodes: int,
) -> npt.NDArray[np.float32]: ...
def grid_advect(
    positions: npt.NDArray[np.float32],
    moving: npt.NDArray[np.bool_],
    velocity: npt.NDArray[np.float32],
    extra: npt.NDArray[np.float32],
    drift: npt.NDArray[np.float32],
    dt: float,
    lo: list[float],
    hi: list[float],
    origin: list[float],
    spacing: list[float],
    nodes: int,
    pressure: tuple[float, float] | None = None,
) -> npt.NDArray[np.float32]: ...
def radius_graph(
    positions: npt.NDArray[np.float32],
    radius: float = ...,
    *,
    self_edges: bool = True,
    max_neighbors: int | None = None,
    max_edges: int | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
def kernel_density(positions: npt.NDArray[np.float32], radius: float) -> npt.NDArray[np.float32]: ...
def relax_density(
    positions: npt.NDArray[np.float32],
    movable: npt.NDArray[np.bool_],
    radius: float,
    rest_density: float,
    iterations: int = 3,
    omega: float = 1.0,
) -> tuple[npt.NDArray[np.float32], int, float]: ...
def relax_then_graph(
    positions: npt.NDArray[np.float32],
    movable: npt.NDArray[np.bool_],
    radius: float,
    rest_density: float,
    iterations: int,
    omega: float,
    bounds: tuple[list[float], list[float]] | None,
    graph_radius: float,
    *,
    self_edges: bool = True,
    max_neighbors: int | None = None,
    max_edges: int | None = None,
) -> tuple[
    npt.NDArray[np.float32],
    int,
    float,
    int,
    int,
    tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.float32]],
]: ...
