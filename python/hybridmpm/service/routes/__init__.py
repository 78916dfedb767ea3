"""The service's routes, one :class:`fastapi.APIRouter` per resource, each
route under its full path (the 405 handler matches the paths of :data:`ROUTERS`)."""

from hybridmpm.service.routes import blocks, bodies, checkpoints, controls, health, materials, obstacles, sessions, steps, stream, trajectory

#: In the order they are included (the page and health first, the stream last).
ROUTERS = (
    health.router,
    materials.router,
    sessions.router,
    steps.router,
    controls.router,
    obstacles.router,
    blocks.router,
    bodies.router,
    trajectory.router,
    checkpoints.router,
    stream.router,
)

__all__ = ["ROUTERS"]
