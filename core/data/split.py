"""Which cameras train and which are held out for evaluation (docs/design.md 3.1, 3.6).

A capture may declare its dataset's held-out cameras (capture.json `test_cameras`; importers fill
them from their datasets' published splits). A run picks one rule (`RunConfig.split`):

- `auto`: the capture's declared cameras when it has them, else every 8th;
- `capture`: the capture's declared cameras (an error when it declares none);
- `every8`: every 8th camera in capture.json order (index % 8 == 0), the NeRF-era convention;
- `none`: every camera trains, as a final product should; the metrics are then computed on the
  training views and labelled so.

Torch-free: the API checks a requested split against the capture before a job exists.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from core.data.capture import Capture

__all__ = ["SPLITS", "CameraSplit", "Split", "camera_split"]

Split = Literal["auto", "capture", "every8", "none"]
SPLITS: tuple[str, ...] = ("auto", "capture", "every8", "none")


@dataclass(frozen=True)
class CameraSplit:
    """The resolved split of one capture."""

    rule: Literal["capture", "every8", "none"]
    """The rule that chose the held-out cameras (`auto` resolved)."""
    training: tuple[str, ...]
    """Camera ids that train, in capture.json order."""
    heldout: tuple[str, ...]
    """Camera ids never trained on (empty with `none`), in capture.json order."""

    @property
    def scored(self) -> tuple[str, ...]:
        """The cameras that held-out renders and metrics use: the held-out ones, or the
        training ones when nothing is held out."""
        return self.heldout or self.training

    @property
    def on_training_views(self) -> bool:
        """True when the metrics are on views the run trained on (rule `none`)."""
        return not self.heldout

    def to_json(self) -> dict:
        """What eval.json and the API report: the rule, the cameras, what the metrics are on."""
        return {"rule": self.rule, "heldout": list(self.heldout),
                "scored_on": "training views" if self.on_training_views else "held-out views",
                "training_cameras": len(self.training)}


def camera_split(capture: Capture, rule: str = "auto") -> CameraSplit:
    """The split of `capture` under `rule` (module docstring); ValueError naming the rule when
    the capture cannot follow it."""
    if rule not in SPLITS:
        raise ValueError(f"split: expected one of {', '.join(SPLITS)}, got {rule!r}")
    ids = [c.id for c in capture.cameras]
    if rule == "auto":
        rule = "capture" if capture.test_cameras else "every8"
    if rule == "capture":
        if not capture.test_cameras:
            raise ValueError("split: the capture declares no test_cameras; choose every8 or "
                             "none")
        held = set(capture.test_cameras)
    elif rule == "every8":
        held = {c for i, c in enumerate(ids) if i % 8 == 0}
    else:
        held = set()
    training = tuple(c for c in ids if c not in held)
    if not training:
        raise ValueError(f"split: {rule} leaves no camera to train on ({len(ids)} camera(s); "
                         "every8 needs at least 2)")
    return CameraSplit(rule, training, tuple(c for c in ids if c in held))  # type: ignore[arg-type]
