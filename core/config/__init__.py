"""The run configuration, typed once (pydantic dataclasses, torch-free): what `dgs reconstruct
--config` reads, what `POST /v1/jobs` validates and `GET /v1/pipelines` publishes as JSON Schema.

Every section is a frozen dataclass that validates when built (`dataclasses.replace` too);
`load_config` lays a preset, a JSON file and request overrides on each other and reports every
bad setting by its path (`ConfigError.details`).
"""

from core.config.base import ConfigError, schema, validate
from core.config.run import (
    MESH_FORMATS,
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

__all__ = [
    "AOConfig",
    "ConfigError",
    "DEVICE_PATTERN",
    "DensifyConfig",
    "InitConfig",
    "LearningRates",
    "LossWeights",
    "MESH_FORMATS",
    "METHODS",
    "MeshConfig",
    "Method",
    "PRESETS",
    "Preset",
    "RunConfig",
    "Schedule",
    "SequenceConfig",
    "StereoConfig",
    "TrainConfig",
    "apply_overrides",
    "load_config",
    "method_defaults",
    "parse_frames",
    "preset_config",
    "schedule_for",
    "schema",
    "train_config",
    "validate",
]
