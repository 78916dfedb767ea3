"""The ``hybridmpm`` command line: the HTTP service and its page (``serve``; needs the ``service`` extra)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from hybridmpm.errors import InvalidInputError


def _serve(args: argparse.Namespace) -> int:
    """``hybridmpm serve``: the HTTP service and its page (one process: sessions live in memory, and in ``--store`` when given)."""
    try:
        # import time: loaded by this command only
        from hybridmpm.service import ServiceConfig, create_app
        from hybridmpm.service.server import run
    except ImportError as e:
        raise InvalidInputError(f"serve: needs the service extra (pip install 'hybridmpm[service]'): {e}", "serve") from None
    hosts = None if args.allowed_hosts is None else tuple(h.strip() for h in args.allowed_hosts.split(",") if h.strip())
    cfg = ServiceConfig.from_env(
        max_sessions=args.max_sessions,
        idle_ttl_s=args.ttl,
        allowed_hosts=hosts,
        max_sessions_per_client=args.max_sessions_per_client,
        memory_budget=args.memory_budget,
        store=args.store,
        save_every_s=args.save_every,
        backend=args.backend,
        ray_address=args.ray_address,
        ray_namespace=args.ray_namespace,
        ray_num_cpus=args.ray_num_cpus,
        realtime=args.realtime,
    )
    app = create_app(cfg)  # opens the store, joins the Ray cluster of --backend ray (a clear error if it cannot)
    print(
        f"hybridmpm: serving on http://{args.host}:{args.port}/ (max {cfg.max_sessions} sessions, {cfg.max_sessions_per_client} per client, "
        f"idle TTL {cfg.idle_ttl_s:g} s, hosts {', '.join(cfg.allowed_hosts) or 'loopback names on loopback addresses'}"
        f"{f', store {cfg.store}, saved every {cfg.save_every_s:g} s' if cfg.store else ''}"
        f"{f', sessions in the Ray cluster at {cfg.ray_address}' if cfg.backend == 'ray' else ('' if cfg.store else ', sessions in memory only')}"
        f"{', sessions in real-time mode by default' if cfg.realtime else ''})",
        file=sys.stderr,
        flush=True,
    )
    run(app, args.host, args.port, cfg, log_level=args.log_level)
    return 0


def add_parsers(sub: Any) -> None:
    """Register this group's commands on the subparsers ``sub``."""
    sv = sub.add_parser("serve", help="the HTTP service and its web page (needs the 'service' extra; one process, sessions in memory)")
    sv.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    sv.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    sv.add_argument("--max-sessions", type=int, default=None, help="sessions held at once; more get 503 (default 100, env HYBRIDMPM_MAX_SESSIONS)")
    sv.add_argument("--ttl", type=float, default=None, help="idle seconds before a session is removed (default 600, env HYBRIDMPM_IDLE_TTL_S)")
    sv.add_argument(
        "--allowed-hosts", default=None,
        help="comma-separated Host names served (others: 400; '*' any). Default (env HYBRIDMPM_ALLOWED_HOSTS): the loopback names on loopback addresses, any elsewhere",
    )  # fmt: skip
    sv.add_argument("--max-sessions-per-client", type=int, default=None, help="sessions one client address may hold; more get 429 (default 20)")
    sv.add_argument(
        "--memory-budget", default=None,
        help="memory for sessions, kept controls and requests together, e.g. 8G; beyond it 503 (default half the RAM, env HYBRIDMPM_SERVICE_MEMORY_BUDGET)",
    )  # fmt: skip
    sv.add_argument(
        "--store", default=None,
        help="directory or fsspec URL (s3://..., memory://...) keeping every session's checkpoint: a restarted server brings them back (env HYBRIDMPM_STORE)",
    )  # fmt: skip
    sv.add_argument(
        "--save-every", type=float, default=None,
        help="with --store: seconds a stepping session goes at most without a save, what a crash can lose (default 1, env HYBRIDMPM_SAVE_EVERY_S)",
    )  # fmt: skip
    sv.add_argument(
        "--backend", default=None,
        help="where sessions live: 'local' (this process, the default) or 'ray' (an actor each on a Ray cluster; any number of front ends; env HYBRIDMPM_BACKEND)",
    )  # fmt: skip
    sv.add_argument("--ray-address", default=None, help="with --backend ray: 'auto' (the cluster `ray start` made here; default) or HOST:PORT of its head")
    sv.add_argument("--ray-namespace", default=None, help="with --backend ray: the Ray namespace of the sessions' actors (default hybridmpm)")
    sv.add_argument("--ray-num-cpus", type=float, default=None, help="with --backend ray: CPUs Ray reserves for each session's actor (default 0.25)")
    sv.add_argument(
        "--realtime", action="store_const", const=True, default=None,
        help="sessions created without 'realtime' run in real-time mode (those of the default solver; docs/service.md; env HYBRIDMPM_REALTIME=1)",
    )  # fmt: skip
    sv.add_argument("--log-level", default="warning", choices=["critical", "error", "warning", "info", "debug"], help="uvicorn log level")
    sv.set_defaults(func=_serve)
