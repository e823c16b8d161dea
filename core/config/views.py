"""Which views a run trains on and scores (docs/design.md 3.1, 3.6): the split rule, and the
view selection it resolves to against a capture (`Views`, part of `core.config.ResolvedRun`).

A capture may declare its dataset's held-out cameras (capture.json `test_cameras`; importers fill
them from their datasets' published splits). A run picks one rule (`RunConfig.split`):

- `auto`: the capture's declared cameras when it has them, else every 8th;
- `capture`: the capture's declared cameras (an error when it declares none);
- `every8`: every 8th camera in capture.json order (index % 8 == 0), the NeRF-era convention;
- `none`: every camera trains, as a final product should; the metrics are then computed on the
  training views and labelled so.

Torch-free: the API resolves a job's views against the capture before the job exists, with the
same functions the command line uses.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from core.config.base import ConfigError, section
from core.data.capture import Camera, Capture

__all__ = ["MASKS", "SPLITS", "CameraSplit", "Masks", "Split", "Views", "camera_split",
           "select_views"]

Split = Literal["auto", "capture", "every8", "none"]
SPLITS: tuple[str, ...] = ("auto", "capture", "every8", "none")
Masks = Literal["capture", "matte", "subject"]
MASKS: tuple[str, ...] = ("capture", "matte", "subject")


@section
class CameraSplit:
    """The resolved split of one capture."""

    rule: Literal["capture", "every8", "none"]
    """The rule that chose the held-out cameras (`auto` resolved)."""
    training: Annotated[tuple[str, ...], Field(min_length=1)]
    """Camera ids that train, in capture.json order."""
    heldout: tuple[str, ...] = ()
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


def _refuse(message: str) -> ConfigError:
    return ConfigError([{"path": "split", "message": message}])


def camera_split(capture: Capture, rule: str = "auto") -> CameraSplit:
    """The split of `capture` under `rule` (module docstring); ConfigError at `split` when the
    capture cannot follow it."""
    if rule not in SPLITS:
        raise _refuse(f"expected one of {', '.join(SPLITS)}, got {rule!r}")
    ids = [c.id for c in capture.cameras]
    if rule == "auto":
        rule = "capture" if capture.test_cameras else "every8"
    if rule == "capture":
        if not capture.test_cameras:
            raise _refuse("the capture declares no test_cameras; choose auto, every8 or none")
        held = set(capture.test_cameras)
    elif rule == "every8":
        held = {c for i, c in enumerate(ids) if i % 8 == 0}
    else:
        held = set()
    training = tuple(c for c in ids if c not in held)
    if not training:
        raise _refuse(f"{rule} leaves no camera to train on (the capture has {len(ids)} "
                      "camera(s); every8 needs at least 2); choose none")
    return CameraSplit(rule, training, tuple(c for c in ids if c in held))  # type: ignore


@section
class Views:
    """The views of a run, resolved against its capture: which cameras train and which are
    scored, at what size, and what the masks mean. Every stage reads these, from training to
    the last export, instead of resolving the rule again."""

    split: CameraSplit
    """The cameras that train and those held out (`RunConfig.split` resolved)."""
    downscale: Annotated[float, Field(ge=1, le=64)] = 1.0
    """The images are reduced by this factor, for training and scoring alike."""
    masks: Literal["matte", "subject"] = "matte"
    """What the masks mean for this run (`TrainConfig.masks`, `capture` resolved): `matte`
    cuts the subject out of each picture; `subject` marks it in a picture reconstructed
    whole (what tracked frames move, what a subject export or mesh keeps)."""

    @property
    def subject(self) -> bool:
        """Whether the masks mark a subject inside a scene (else they are a matte, or absent)."""
        return self.masks == "subject"

    @property
    def matte(self) -> bool:
        return self.masks == "matte"

    def served(self, camera: Camera) -> Camera:
        """`camera` at the run's resolution (reduced by `downscale`)."""
        return camera.scaled(max(1, round(camera.width / self.downscale)),
                             max(1, round(camera.height / self.downscale)))

    def cameras(self, capture: Capture, which: Literal["training", "scored"]) -> list[Camera]:
        """The capture's training or scored cameras, in capture.json order."""
        ids = set(self.split.training if which == "training" else self.split.scored)
        return [c for c in capture.cameras if c.id in ids]


def select_views(capture: Capture, split: str = "auto", downscale: float = 1.0,
                 masks: str = "capture") -> Views:
    """The one place a run's views are resolved: `split` (`camera_split`), `downscale`, and
    `masks` (`capture`: what capture.json says). ConfigError naming the setting."""
    if masks not in MASKS:
        raise ConfigError([{"path": "train.masks", "message": f"expected one of "
                            f"{', '.join(MASKS)}, got {masks!r}"}])
    resolved = capture.masks if masks == "capture" else masks
    return Views(camera_split(capture, split), downscale, resolved)  # type: ignore[arg-type]
