"""The run configuration, typed once (pydantic dataclasses, torch-free): what `dgs reconstruct
--config` reads, what `POST /v1/jobs` validates and `GET /v1/pipelines` publishes as JSON Schema;
and the run it resolves to against a capture (`ResolvedRun`: frames, views, configuration), made
once and carried whole to every stage (RUN/config.json), with the rules it is resolved by: which
views train and are scored (`views`), how frames group (`groups`).

Every section is a frozen dataclass that validates when built (`dataclasses.replace` too);
`load_config` lays a preset, a JSON file and request overrides on each other and reports every
bad setting by its path (`ConfigError.details`).
"""

from core.config.base import ConfigError, schema, validate
from core.config.groups import (
    FrameRole,
    Gop,
    frames_per_group,
    independent_groups,
    roles,
    segment,
)
from core.config.resolved import CONFIG_VERSION, ResolvedRun, read_run, resolve_run, upgrade
from core.config.run import (
    MESH_FORMATS,
    CheckpointEvery,
    GopSize,
    MeshConfig,
    RunConfig,
    apply_overrides,
    load_config,
    parse_frames,
    preset_config,
)
from core.config.rig import StereoConfig
from core.config.sequence import SequenceConfig
from core.config.train import (
    DEVICE_PATTERN,
    METHODS,
    PRESETS,
    AOConfig,
    DensifyConfig,
    InitConfig,
    LearningRates,
    LossWeights,
    Method,
    Preset,
    Schedule,
    TrainConfig,
    method_defaults,
    schedule_for,
    train_config,
)
from core.config.views import (
    SPLITS,
    CameraSplit,
    Split,
    Views,
    camera_split,
    select_views,
)

__all__ = [
    "AOConfig",
    "CONFIG_VERSION",
    "CameraSplit",
    "CheckpointEvery",
    "ConfigError",
    "DEVICE_PATTERN",
    "DensifyConfig",
    "FrameRole",
    "Gop",
    "GopSize",
    "InitConfig",
    "LearningRates",
    "LossWeights",
    "MESH_FORMATS",
    "METHODS",
    "MeshConfig",
    "Method",
    "PRESETS",
    "Preset",
    "ResolvedRun",
    "RunConfig",
    "SPLITS",
    "Schedule",
    "SequenceConfig",
    "Split",
    "StereoConfig",
    "TrainConfig",
    "Views",
    "apply_overrides",
    "camera_split",
    "frames_per_group",
    "independent_groups",
    "load_config",
    "method_defaults",
    "parse_frames",
    "preset_config",
    "read_run",
    "resolve_run",
    "roles",
    "schedule_for",
    "schema",
    "segment",
    "select_views",
    "train_config",
    "upgrade",
    "validate",
]
