"""Server folders out of what clients read: an error a library raised about a file under the
data folder names it by its full path on this machine; clients know it by the path inside
their capture (or not at all). `redact` rewrites such paths before a message is stored or
answered."""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

__all__ = ["SERVER", "redact"]

SERVER = "<server>"
"""What a folder of the server that means nothing to a client is shown as."""


def redact(text: str, roots: Iterable[tuple[Path | str | None, str]]) -> str:
    """`text` with every path under one of `roots` written from that root on: each
    (root, label) pair replaces `root/` by `label/` (by nothing when the label is empty, so
    the path becomes relative to the root) and the bare root by the label (or '.'). Longer
    roots go first, so a capture folder inside the data folder keeps its relative paths."""
    pairs = sorted(((str(r).rstrip(os.sep), label) for r, label in roots if r),
                   key=lambda p: len(p[0]), reverse=True)
    for root, label in pairs:
        if not root or root not in text:
            continue
        # The root itself or followed by a separator, not a longer name that starts with it.
        pattern = re.compile(re.escape(root) + rf"({re.escape(os.sep)}|(?![\w.\-]))")
        text = pattern.sub(lambda m, label=label: (f"{label}/" if label else "") if m[1]
                           else (label or "."), text)
    return text
