"""The page at ``/`` (and its particle-type codes, ``/codes.js``), ``/healthz`` (with the solvers a session
may ask for and whether sessions default to real-time mode, ``serve --realtime``) and the scene list."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, Response

from hybridmpm import __version__
from hybridmpm.control.controller import scene_methods
from hybridmpm.conventions import GNS_ELASTIC, GNS_GOOP, GNS_KINEMATIC, GNS_SAND, GNS_SNOW, GNS_WATER
from hybridmpm.models import shipped_default, shipped_models
from hybridmpm.scenes import DOMAINS
from hybridmpm.service.deps import ConfigDep, ManagerDep
from hybridmpm.service.schemas import Health, SceneInfo
from hybridmpm.sim import SOLVERS

STATIC = Path(__file__).parent.parent / "static"
CSP = "default-src 'self'; img-src 'self' data:; connect-src 'self'; style-src 'self'; script-src 'self'; object-src 'none'; base-uri 'none'"

#: The page's names of the GNS particle-type codes: ``static/*.js`` import them from ``/codes.js``, made here from
#: :mod:`hybridmpm.conventions` (the page writes no number of its own)
PAGE_CODES = {"WALL": GNS_KINEMATIC, "WATER": GNS_WATER, "SAND": GNS_SAND, "MUD": GNS_GOOP, "JELLY": GNS_ELASTIC, "SNOW": GNS_SNOW}
CODES_JS = "// the GNS particle-type codes of hybridmpm.conventions, as the page names them\n" + "".join(
    f"export const {name} = {code};\n" for name, code in PAGE_CODES.items()
)

router = APIRouter()


def scene_list() -> list[dict[str, Any]]:
    ships = shipped_models()
    out = []
    for name, gen in sorted(DOMAINS.items()):
        spec = gen(seed=0)
        doc = (gen.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
        has = name in ships
        offered = scene_methods(name)  # the classical methods, diffusion where its controller ships, and the scene's default
        default = shipped_default(name)
        out.append(
            {
                "name": name,
                "dim": int(spec.params.dim),
                "frames": int(spec.frames),
                "seeded": spec.blocks != gen(seed=1).blocks,  # whether two seeds differ, not a list of names
                "doc": " ".join(doc.split()),
                "solvers": [x for x in SOLVERS if has or x in ("default", "mpm", "realtime")],  # real-time mode: MPM, on every scene
                "default_configuration": default.get("label") or "MPM on the scene as given",
                "model": has,
                "methods": offered["methods"],
                "default_method": offered["default"],
            }
        )
    return out


@router.get("/", include_in_schema=False)
async def page() -> FileResponse:
    return FileResponse(STATIC / "index.html", headers={"Content-Security-Policy": CSP, "Cache-Control": "no-cache"})


@router.get("/codes.js", include_in_schema=False)
async def codes() -> Response:
    return Response(CODES_JS, media_type="text/javascript", headers={"Cache-Control": "no-cache"})


@router.get("/healthz", response_model=Health)
async def healthz(manager: ManagerDep, cfg: ConfigDep) -> dict[str, Any]:
    return {
        "status": "ok",
        "sessions": await manager.held(),
        "max_sessions": cfg.max_sessions,
        "memory_used": manager.budget.used,
        "memory_budget": manager.budget.total,
        "version": __version__,
        "solvers": list(SOLVERS),
        "realtime_default": cfg.realtime,
    }


@router.get("/v1/scenes", response_model=list[SceneInfo])
async def scenes(request: Request, manager: ManagerDep) -> list[dict[str, Any]]:
    cache: list[dict[str, Any]] = request.app.state.scenes
    if not cache:
        cache.extend(await manager.compute(scene_list))
    return cache
