"""Progress bars of a job followed through its server-sent events, drawn by tqdm: one for the job
and, for a job run as parts (docs/design.md 4.4), one per running part, redrawn in place on a
terminal; on anything else a line whenever the job or a part passes a tenth or changes stage or
state. The fraction and the ETA are the server's (a resumed job's own rate), not tqdm's."""

from __future__ import annotations

import sys
from typing import Any, TextIO

from tqdm import tqdm

from service.client.http import Event

__all__ = ["JobBars", "bar_line"]

_FORMAT = "{desc}[{bar:%d}] {percentage:5.1f}%%  {detail}"
_ASCII = ".#"


def _detail(p: dict[str, Any]) -> str:
    """`stage  frame f/n step i/n  ETA` of a progress object."""
    text = f"{p.get('stage') or '':<11}"
    if p.get("frames"):
        text += f" frame {p.get('frame', 0)}/{p['frames']}"
    if p.get("iterations"):
        text += f" step {p.get('iteration', 0)}/{p['iterations']}"
    if p.get("eta_s") is not None:
        text += f"  ETA {tqdm.format_interval(p['eta_s'])}"
    return text


def _fraction(p: dict[str, Any]) -> float:
    return min(max(float(p.get("fraction") or 0.0), 0.0), 1.0)


def bar_line(label: str, p: dict[str, Any], width: int = 30) -> str:
    """`label [#####.....]  50.0%  stage  frame f/n step i/n  ETA mm:ss`."""
    return tqdm.format_meter(_fraction(p), 1.0, 0, prefix=label, ascii=_ASCII,
                             bar_format=_FORMAT % width, detail=_detail(p))


class _Bar(tqdm):
    """A tqdm bar whose text after the bar is a progress object's `_detail`."""

    def __init__(self, *args: Any, detail: str = "", **kwargs: Any):
        self.detail = detail  # before tqdm draws the bar the first time
        super().__init__(*args, **kwargs)

    @property
    def format_dict(self) -> dict[str, Any]:
        return {**super().format_dict, "detail": self.detail}


class JobBars:
    """Feed it every event (`on_event`); `close()` at the end."""

    def __init__(self, stream: TextIO | None = None, width: int = 30):
        self.stream = stream or sys.stdout
        self.width, self.tty = width, self.stream.isatty()
        self.job: dict[str, Any] = {}
        self.parts: dict[int, dict[str, Any]] = {}
        self._bars: dict[object, _Bar] = {}
        self._positions: dict[object, int] = {}
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
        return [(key, bar_line(label, p, self.width), p) for key, label, p in self._shown()]

    def _shown(self) -> list[tuple[object, str, dict[str, Any]]]:
        out: list[tuple[object, str, dict[str, Any]]] = [("job", "      ", self.job)]
        for index in sorted(self.parts):
            p = self.parts[index]
            if p.get("state") == "running":
                out.append((index, f"  part {index:>3} ", p))
        return out

    def draw(self) -> None:
        if self.tty:
            self._draw_bars()
            return
        for key, text, p in self.lines():
            mark = (int(_fraction(p) * 10), p.get("stage"), p.get("state"))
            if self._seen.get(key) != mark:
                self._seen[key] = mark
                self.stream.write(text + "\n")
        self.stream.flush()

    def _draw_bars(self) -> None:
        """One tqdm bar per shown line, at a fixed position; a part's bar goes when it ends."""
        shown = self._shown()
        for key in [k for k in self._bars if k not in {k for k, _, _ in shown}]:
            self._close(key)
        for key, label, p in shown:
            bar = self._bars.get(key)
            if bar is None:
                taken = set(self._positions.values())
                position = self._positions[key] = min(set(range(len(taken) + 1)) - taken)
                self._bars[key] = _Bar(
                    total=1.0, initial=_fraction(p), detail=_detail(p), desc=label,
                    file=self.stream, position=position, leave=key == "job", ascii=_ASCII,
                    bar_format=_FORMAT % self.width, mininterval=0)
                continue
            bar.n, bar.detail = _fraction(p), _detail(p)
            bar.refresh()

    def _close(self, key: object) -> None:
        self._bars.pop(key).close()
        del self._positions[key]

    def close(self) -> None:
        """Close the parts' bars, then the job's (left on the terminal)."""
        for key in sorted(self._bars, key=lambda k: k == "job"):
            self._close(key)
