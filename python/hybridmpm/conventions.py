"""Codes and defaults of hybridmpm, defined once (docs/design.md "Conventions").

Every other module imports these names; none restates the numbers.

Two code tables exist and they are *different*:

* **solver material codes** (:data:`MATERIALS`, the core's ``_core.MATERIAL_CODES``:
  :data:`MATERIAL_WATER` 0, :data:`MATERIAL_SAND` 1, :data:`MATERIAL_ELASTIC` 2,
  :data:`MATERIAL_SNOW` 3, :data:`MATERIAL_VISCOPLASTIC` 4, and any further model
  of the core's registry): what the Rust MPM solver stores per particle
  (``MpmSolver.material``; ``Material`` in ``rust/mpm/src/material/codes.rs``);
* **GNS particle-type codes** (:data:`GNS_KINEMATIC` 3, :data:`GNS_WATER` 5,
  :data:`GNS_SAND` 6; DeepMind ``learning_to_simulate``): what datasets,
  trajectories and the network see (``particle_type``). Boundary / obstacle
  particles exist only here.

:data:`GNS_TYPE_OF_MATERIAL` maps the first table onto the second.
"""

from __future__ import annotations

from hybridmpm import _core

# ----------------------------------------------------------------- codes
#: Solver material codes by name (scene files say ``material = "water"``): the
#: core's registry, one entry per constitutive model in code order
#: (``_core.MATERIAL_CODES``, from the ``materials!`` list of
#: ``rust/mpm/src/material/codes.rs``).
MATERIALS: dict[str, int] = dict(_core.MATERIAL_CODES)
#: Solver material code of weakly compressible water.
MATERIAL_WATER = MATERIALS["water"]
#: Solver material code of Drucker–Prager sand.
MATERIAL_SAND = MATERIALS["sand"]
#: Solver material code of the elastic solid (fixed-corotated or neo-Hookean).
MATERIAL_ELASTIC = MATERIALS["elastic"]
#: Solver material code of snow (Stomakhin et al. 2013).
MATERIAL_SNOW = MATERIALS["snow"]
#: Solver material code of the viscoplastic solid (von Mises with viscous relaxation).
MATERIAL_VISCOPLASTIC = MATERIALS["viscoplastic"]
#: The materials the learned simulators and the diffusion controller were
#: trained on (they refuse a scene holding any other, naming it).
LEARNED_MATERIALS: tuple[str, ...] = ("water", "sand")

#: GNS particle type of kinematic (static boundary / obstacle) particles.
GNS_KINEMATIC = 3
#: GNS particle type of water.
GNS_WATER = 5
#: GNS particle type of sand.
GNS_SAND = 6
#: GNS particle type of the viscoplastic solid (the GNS datasets' "goop").
GNS_GOOP = 7
#: GNS particle type of the elastic solid (past the GNS datasets' codes).
GNS_ELASTIC = 8
#: GNS particle type of snow (past the GNS datasets' codes).
GNS_SNOW = 9
#: The GNS particle types given by name; a model of the core not named here gets the next free
#: type past them (:func:`gns_types`).
_GNS_NAMED = {"water": GNS_WATER, "sand": GNS_SAND, "elastic": GNS_ELASTIC, "snow": GNS_SNOW, "viscoplastic": GNS_GOOP}


def gns_types(materials: dict[str, int]) -> dict[int, int]:
    """The GNS particle type of each solver material code of ``materials`` (``{name: code}``): the
    named type of :data:`_GNS_NAMED` where it has one, else the types past the largest named one
    (10, 11, ...), in code order, so that every model of the core has one, the same on every run."""
    out: dict[int, int] = {}
    nxt = max(_GNS_NAMED.values()) + 1
    for name, code in sorted(materials.items(), key=lambda item: item[1]):
        if name in _GNS_NAMED:
            out[code] = _GNS_NAMED[name]
        else:
            out[code], nxt = nxt, nxt + 1
    return out


#: GNS particle type of each solver material (:func:`gns_types` of :data:`MATERIALS`).
GNS_TYPE_OF_MATERIAL = gns_types(MATERIALS)
#: Material name of each fluid GNS particle type (exported meshes and files are named by it).
NAME_OF_GNS_TYPE = {GNS_TYPE_OF_MATERIAL[code]: name for name, code in MATERIALS.items()}

# ----------------------------------------------------------------- units and resolutions
#: One frame of simulated time [s] (made of CFL substeps in MPM).
DT_FRAME = 2.5e-3
#: Default grid cells per dimension, by dimension (128² in 2D, 64³ in 3D).
DEFAULT_N_GRID = {2: 128, 3: 64}
#: Default connectivity radius R [m] of the network's radius graph (2D scenes).
#: Values are defined once in Rust: this is the neighbour-search crate's
#: ``CONNECTIVITY_RADIUS`` (also ``_core.radius_graph``'s default), as its decimal.
CONNECTIVITY_RADIUS: float = _core.CONNECTIVITY_RADIUS
#: Standard gravity [m/s²], the unit ``g`` in which accelerations are reported
#: (control effort, the hybrid's MPM audit).
G = 9.8

# ----------------------------------------------------------------- the method's symbols (paper)
#: Positions the network reads per step (the current one and T_in − 1 before it).
T_IN = 6
#: Frames a control episode covers (paper Sec. 3.2).
T_CTR = 100
#: Safeguard threshold r_c: MPM while s(t) < r_c (paper Table 2, Fig. 6d).
R_C = 0.8
#: Safeguard window δ in coarse steps (paper Sec. 3.1.2).
DELTA = 10
#: Network steps per MPM audit of the hybrid (not in the paper; docs/hybrid.md
#: "The MPM audit": one MPM step at r_p per audit).
AUDIT_EVERY = 4
#: MPM audit tolerance [g]: RMS one-step acceleration difference between the
#: network and MPM from the same state above which MPM takes over.
AUDIT_TOL = 1.0
#: The hybrid's switching rules (docs/hybrid.md "Switching rules"): "paper", the
#: complexity score s(t) alone (paper Sec. 3.1.2); "audit", s(t) plus the MPM
#: audit every AUDIT_EVERY network steps; "error", the network's error alone:
#: an MPM audit whose interval adapts to the measured disagreement, brought
#: forward by the step's density residual.
SAFEGUARDS: tuple[str, ...] = ("audit", "error", "paper")
#: The rule HybridSimulator runs by default.
SAFEGUARD = "audit"
#: "error" rule: the longest interval [network steps] between two audits.
AUDIT_MAX = 16
#: "error" rule: a step whose density residual (the RMS correction of the
#: density relaxation, as an acceleration in g) exceeds this is audited at once.
RESIDUAL_TOL = 0.5

# ----------------------------------------------------------------- the network's failure checks
#: A network step fails ("energy") when it raises the kinetic energy above this
#: factor times the energy available at the start (kinetic + potential above
#: the floor); hybridmpm.sim.neural's module doc has every check.
FAILURE_KE_FACTOR = 2.0
#: ... ("escaped") when it moves a particle more than this many grid cells
#: beyond the model's bounds.
FAILURE_ESCAPE_CELLS = 4.0
#: ... ("compressed") when the mean number of neighbours within R exceeds this
#: factor times that of the initial condition.
FAILURE_DEGREE_FACTOR = 2.0

# ----------------------------------------------------------------- datasets
#: Splits of a GNS-layout dataset, in order.
SPLITS: tuple[str, ...] = ("train", "valid", "test")

__all__ = [
    "NAME_OF_GNS_TYPE",
    "AUDIT_EVERY",
    "AUDIT_MAX",
    "AUDIT_TOL",
    "CONNECTIVITY_RADIUS",
    "DEFAULT_N_GRID",
    "DELTA",
    "DT_FRAME",
    "FAILURE_DEGREE_FACTOR",
    "FAILURE_ESCAPE_CELLS",
    "FAILURE_KE_FACTOR",
    "G",
    "GNS_ELASTIC",
    "GNS_GOOP",
    "GNS_KINEMATIC",
    "GNS_SAND",
    "GNS_SNOW",
    "GNS_TYPE_OF_MATERIAL",
    "GNS_WATER",
    "LEARNED_MATERIALS",
    "MATERIALS",
    "MATERIAL_ELASTIC",
    "MATERIAL_SAND",
    "MATERIAL_SNOW",
    "MATERIAL_VISCOPLASTIC",
    "MATERIAL_WATER",
    "RESIDUAL_TOL",
    "R_C",
    "SAFEGUARD",
    "SAFEGUARDS",
    "SPLITS",
    "T_CTR",
    "T_IN",
    "gns_types",
]
