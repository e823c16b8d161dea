"""The main job (docs/design.md 2.3): `reconstruct` a capture's frames into a run directory.
run (the loop over frames), frame (one frame from its fitter to its outputs), record (what
metrics.json keeps of a frame), outputs (held-out renders, meshes), events (progress, stop)."""

from core.pipeline.events import Progress, Stopped
from core.pipeline.outputs import render_heldout
from core.pipeline.record import FrameRecord
from core.pipeline.run import reconstruct

__all__ = ["FrameRecord", "Progress", "Stopped", "reconstruct", "render_heldout"]
