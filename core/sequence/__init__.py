"""Volumetric video (docs/design.md section 5.9): groups of pictures whose first frame gets the
static stages and whose other frames are the previous frame's Gaussians deformed by an embedded
deformation graph, then refined with temporal regularisation, keeping Gaussian correspondences
(track ids) inside a group.

plan (each tracked frame's inputs, sequence.json; the groups are `core.config.groups`'), tracker
(deform + refine on the shared fitting loop), deform and graph (the deformation), starts and
motion (where the deform stage begins), refine (temporal losses, tracked densification), budget
(refine rate control), tracks (frame PLYs with track ids), metrics and correspondence (flicker,
track error)."""

from core.sequence.budget import median_deform_loss, refine_credit, refine_steps
from core.sequence.correspondence import track_errors
from core.sequence.deform import DeformedGaussians, blur, blur_sigma, deform_losses
from core.sequence.graph import (
    DeformationGraph,
    arap_loss,
    blend_weights,
    build_graph,
    farthest_point_sampling,
    quat_multiply,
    quat_norm_loss,
)
from core.sequence.motion import align_tracks, predict_node_motion, predict_node_motion_second_order
from core.sequence.plan import GopPlan, TrackedInputs
from core.sequence.refine import (
    TemporalWeights,
    TrackedState,
    anchors_of,
    anisotropy_loss,
    prune_transparent,
    relabel,
    temporal_loss,
)
from core.sequence.starts import StartRace, candidate_starts, race_starts, view_order
from core.sequence.tracker import FrameTracker
from core.sequence.tracks import load_frame, save_frame, tracker_for

__all__ = [
    "DeformationGraph",
    "DeformedGaussians",
    "FrameTracker",
    "GopPlan",
    "StartRace",
    "TemporalWeights",
    "TrackedInputs",
    "TrackedState",
    "align_tracks",
    "anchors_of",
    "anisotropy_loss",
    "arap_loss",
    "blend_weights",
    "blur",
    "blur_sigma",
    "build_graph",
    "candidate_starts",
    "deform_losses",
    "farthest_point_sampling",
    "load_frame",
    "median_deform_loss",
    "predict_node_motion",
    "predict_node_motion_second_order",
    "prune_transparent",
    "quat_multiply",
    "quat_norm_loss",
    "race_starts",
    "refine_credit",
    "refine_steps",
    "relabel",
    "save_frame",
    "temporal_loss",
    "track_errors",
    "tracker_for",
    "view_order",
]
