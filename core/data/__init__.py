"""Captures: the canonical layout, validation, importers and the training-time dataset.

The dataset (which needs torch) is imported on first use, so validating and importing captures
stays torch-free for the API process.
"""

from __future__ import annotations

from typing import Any

from core.data.capture import (
    Camera,
    Capture,
    CaptureError,
    Problem,
    View,
    save_capture,
)
from core.data.importers import detect_format, import_capture, read_source
from core.data.schema import load_capture
from core.data.validate import check_capture, validate_capture

__all__ = [
    "ByteLRUCache",
    "Camera",
    "Capture",
    "CaptureDataset",
    "CaptureError",
    "Problem",
    "Sample",
    "View",
    "check_capture",
    "detect_format",
    "import_capture",
    "load_capture",
    "read_source",
    "save_capture",
    "validate_capture",
]

_LAZY = {"ByteLRUCache", "CaptureDataset", "Sample"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        # lazy: the dataset needs torch; the API reads and validates captures with this package
        from core.data import dataset

        return getattr(dataset, name)
    raise AttributeError(f"module 'core.data' has no attribute {name!r}")
