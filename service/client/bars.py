"""Progress bars of a job followed through its server-sent events: one for the job and, for a job
run as parts (docs/design.md 4.4), one per running part, redrawn in place on a terminal; on
anything else a line whenever the job or a part passes a tenth or changes stage or state."""

from __future__ import annotations

import sys
from typing import Any, TextIO

from service.client.http import Event

__all__ = ["JobBars", "bar_line"]


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


def bar_line(label: str, p: dict[str, Any], width: int = 30) -> str:
    """`label [#####.....]  50.0%  stage  frame f/n step i/n  ETA`."""
    fraction = float(p.get("fraction") or 0.0)
    filled = int(round(fraction * width))
    text = f"{label}[{'#' * filled}{'.' * (width - filled)}] {fraction:6.1%}  " \
           f"{p.get('stage') or '':<11}"
    if p.get("frames"):
        text += f" frame {p.get('frame', 0)}/{p['frames']}"
    if p.get("iterations"):
        text += f" step {p.get('iteration', 0)}/{p['iterations']}"
    if p.get("eta_s") is not None:
        text += f"  ETA {_duration(p['eta_s'])}"
    return text


class JobBars:
    """Feed it every event (`on_event`); `close()` at the end."""

    def __init__(self, stream: TextIO | None = None, width: int = 30):
        self.stream = stream or sys.stdout
        self.width, self.tty = width, self.stream.isatty()
        self.job: dict[str, Any] = {}
        self.parts: dict[int, dict[str, Any]] = {}
        self._drawn = 0
        self._seen: dict[object, tuple] = {}

    def on_event(self, event: Event) -> None:
        data = event.data
        if event.kind == "part":
            part = self.parts.setdefault(int(data["part"]), {})
            part.update({k: v for k, v in data.items() if k not in ("part", "event")})
            if data.get("event") == "progress":  # only a running part makes progress
                part["state"] = "running"
        elif event.kind in ("progress", "state") and "fraction" in data:
            self.job.update(data)
        else:
            return
        self.draw()

    def lines(self) -> list[tuple[object, str, dict[str, Any]]]:
        """(key, text, progress) of the job and each running part."""
        out: list[tuple[object, str, dict[str, Any]]] = [
            ("job", bar_line("      ", self.job, self.width), self.job)]
        for index in sorted(self.parts):
            p = self.parts[index]
            if p.get("state") == "running":
                out.append((index, bar_line(f"  part {index:>3} ", p, self.width), p))
        return out

    def draw(self) -> None:
        lines = self.lines()
        if self.tty:
            up = f"\x1b[{self._drawn - 1}F" if self._drawn > 1 else "\r"
            self.stream.write(up + "\n".join(t.ljust(110) + "\x1b[K" for _, t, _ in lines))
            self._drawn = len(lines)
        else:
            for key, text, p in lines:
                mark = (int(float(p.get("fraction") or 0) * 10), p.get("stage"), p.get("state"))
                if self._seen.get(key) != mark:
                    self._seen[key] = mark
                    self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = 0
