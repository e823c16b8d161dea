"""`python -m service.openapi > openapi.yaml`: the app's OpenAPI document as stable YAML (sorted
keys), the contract committed at the repository root (docs/design.md section 2)."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import yaml

from service.app import create_app
from service.settings import ServiceSettings

__all__ = ["openapi_yaml"]


def openapi_yaml() -> str:
    """The document of an app on default limits (a throw-away data folder, so nothing local
    leaks into it)."""
    with tempfile.TemporaryDirectory(prefix="dgs-openapi-") as tmp:
        fields = {"data_dir": Path(tmp), "database_url": None, "broker_url": None,
                  "storage_url": None, "public_url": None, "retention_days": None}
        app = create_app(ServiceSettings(_env_file=None, **fields))
        schema = app.openapi()
    return yaml.safe_dump(schema, sort_keys=True, allow_unicode=True, width=100)


if __name__ == "__main__":
    sys.stdout.write(openapi_yaml())
