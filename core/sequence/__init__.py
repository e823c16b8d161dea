"""Volumetric video (DESIGN.md section 5, Sequence): groups of pictures whose first frame gets the
static stages and whose other frames are the previous frame's Gaussians deformed by an embedded
deformation graph, then refined with temporal regularisation, keeping Gaussian correspondences
(track ids) inside a group."""

from core.sequence.budget import median_deform_loss, refine_credit, refine_steps
from core.sequence.correspondence import track_errors
from core.sequence.deform import DeformedGaussians, blur, blur_sigma, deform_losses
from core.sequence.frame import FrameTracker
from core.sequence.gop import FrameRole, Gop, roles, roles_of, segment, with_rekeys
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
from core.sequence.refine import (
    TemporalWeights,
    TrackedState,
    anchors_of,
    anisotropy_loss,
    prune_transparent,
    relabel,
    temporal_loss,
)
from core.sequence.rounds import DeformRounds, RoundEnd
from core.sequence.run import load_frame, save_frame, sequence_record, tracker_from_capture
from core.sequence.starts import StartRace, candidate_starts, race_starts, view_order

__all__ = [
    "DeformRounds",
    "DeformationGraph",
    "DeformedGaussians",
    "FrameRole",
    "FrameTracker",
    "Gop",
    "RoundEnd",
    "StartRace",
    "TemporalWeights",
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
    "roles",
    "roles_of",
    "save_frame",
    "segment",
    "with_rekeys",
    "sequence_record",
    "temporal_loss",
    "track_errors",
    "tracker_from_capture",
    "view_order",
]
