"""`dgs serve` and `dgs keys create|list|revoke` (registered through the dgs.commands entry
point, so core never imports the service); and `dgs demo` is taken over to run through the
service (service.demo) when the service extra's packages are installed."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the HTTP API (and an embedded worker by default)")
    p.add_argument("--host", default=None, help="interface (default 127.0.0.1; anything else "
                                                "needs an API key to exist)")
    p.add_argument("--port", type=int, default=None, help="TCP port (default 8000)")
    p.add_argument("--data-dir", type=Path, default=None,
                   help="where the embedded default keeps its state (default DGS_DATA_DIR or "
                        "~/.local/share/dgs)")
    p.add_argument("--no-worker", action="store_true",
                   help="do not start the embedded worker (run `dgs worker` yourself)")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="embedded workers (default 1): a sequence's groups of pictures run on "
                        "N at once, each with the cores divided by N")
    p.set_defaults(func=_serve)

    k = sub.add_parser("keys", help="create, list and revoke API keys")
    ksub = k.add_subparsers(dest="keys_command", metavar="SUBCOMMAND")
    ksub.required = True
    c = ksub.add_parser("create", help="create a key (printed once, never stored)")
    c.add_argument("--tenant", required=True, help="whose captures and jobs the key reaches")
    c.add_argument("--name", default="", help="a note: who or what uses the key")
    c.set_defaults(func=_create)
    ksub.add_parser("list", help="list keys (never their secrets)").set_defaults(func=_list)
    r = ksub.add_parser("revoke", help="revoke a key at once")
    r.add_argument("key_id", help="the id column of `dgs keys list`")
    r.set_defaults(func=_revoke)

    # core registers `dgs demo` before the entry points are loaded (core.cli.build_parser)
    demo = sub.choices.get("demo")
    if demo is not None:
        demo.set_defaults(func=_demo)


def _missing_service_packages() -> list[str]:
    # lazy: `dgs` starts without the service extra installed
    from importlib.util import find_spec

    return [name for name in ("fastapi", "uvicorn", "httpx", "sqlalchemy", "celery",
                              "pydantic_settings") if find_spec(name) is None]


def _demo(args: argparse.Namespace) -> int:
    # lazy: the demo imports torch, which `dgs serve` and the API process must not load
    from core.demo import run_demo, run_raster_demo

    if args.raster:
        return run_raster_demo(args.out)
    if args.in_process:
        return run_demo(args.out)
    missing = _missing_service_packages()
    if missing:
        print(f"dgs demo: the service extra is not installed ({', '.join(missing)} missing), "
              "so the job runs in this process (pip install -e '.[service]' to run it through "
              "the HTTP service)", flush=True)
        return run_demo(args.out)
    # lazy: `dgs` starts without the service extra installed
    from service.demo import run_service_demo

    try:
        return run_service_demo(args.out)
    except RuntimeError as exc:
        print(f"dgs demo: {exc}", file=sys.stderr)
        return 1


def _settings(args: argparse.Namespace):
    # lazy: `dgs` starts without the service extra installed
    from service.settings import ServiceSettings

    overrides = {k: v for k, v in (("host", getattr(args, "host", None)),
                                   ("port", getattr(args, "port", None)),
                                   ("data_dir", getattr(args, "data_dir", None)))
                 if v is not None}
    return ServiceSettings(**overrides)


def _serve(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the service extra installed
    from pydantic import ValidationError
    # lazy: as above
    from worker.settings import describe

    if args.workers < 1:
        print(f"dgs serve: --workers: expected at least 1, got {args.workers}", file=sys.stderr)
        return 2
    try:  # before anything that reads the settings (worker.app reads them at import)
        settings = _settings(args)
    except ValidationError as exc:
        print(f"dgs serve: {describe(exc)}", file=sys.stderr)
        return 2
    # lazy: after the settings are known good
    from service.serve import serve

    return serve(settings, worker=not args.no_worker, workers=args.workers)


def _database(args: argparse.Namespace) -> str:
    # lazy: `dgs` starts without the service extra installed
    from worker.db import migrate

    url = _settings(args).database
    migrate(url)
    return url


def _create(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the service extra installed
    from service.auth import LOCAL_TENANT, create_key, tenant_holdings

    url = _database(args)
    try:
        row, key = create_key(url, args.tenant, args.name)
    except ValueError as exc:
        print(f"dgs keys create: {exc}", file=sys.stderr)
        return 2
    local = {k: n for k, n in tenant_holdings(url, LOCAL_TENANT).items() if n}
    if local and row.tenant != LOCAL_TENANT:
        what = ", ".join(f"{n} {kind[:-1]}(s)" for kind, n in local.items())
        print(f"dgs keys create: note: {what} were made before any key existed (tenant "
              f"{LOCAL_TENANT!r}); from now on every request needs a key, and this key (tenant "
              f"{row.tenant!r}) does not reach them. A key made with --tenant {LOCAL_TENANT} "
              "does.", file=sys.stderr)
    print(f"created key {row.id} for tenant {row.tenant}. Store it now; it is not shown "
          f"again:\n{key}")
    return 0


def _when(value) -> str:
    return value.strftime("%Y-%m-%d %H:%M:%SZ") if value is not None else "-"


def _list(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the service extra installed
    from service.auth import list_keys

    rows = list_keys(_database(args))
    print(f"{'id':16}  {'tenant':16}  {'name':20}  {'created':20}  {'last used':20}  revoked")
    for r in rows:
        print(f"{r.id:16}  {r.tenant:16}  {r.name[:20]:20}  {_when(r.created_at):20}  "
              f"{_when(r.last_used_at):20}  {_when(r.revoked_at)}")
    return 0


def _revoke(args: argparse.Namespace) -> int:
    # lazy: `dgs` starts without the service extra installed
    from service.auth import revoke_key

    row = revoke_key(_database(args), args.key_id)
    if row is None:
        print(f"dgs keys revoke: no key {args.key_id!r} (see `dgs keys list`)", file=sys.stderr)
        return 1
    print(f"revoked key {row.id} (tenant {row.tenant})")
    return 0
