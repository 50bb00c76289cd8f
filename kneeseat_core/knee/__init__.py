"""The joint: a knee config (bodies, meshes, attitude axes, pushes, grid, settle parameters)
and the embedded default knee (`synth`, built from the smooth solids of `solids`)."""
from .config import (BodySpec, config_from_metadata, grid_values, KneeConfig,
                     ligaments_from_metadata, load_config, neutral_pose)
from .synth import DEFAULT_CONFIG, default_knee, default_knee_dir, materialise_default_knee

__all__ = ['BodySpec', 'KneeConfig', 'load_config', 'grid_values', 'neutral_pose',
           'config_from_metadata', 'ligaments_from_metadata', 'DEFAULT_CONFIG', 'default_knee',
           'default_knee_dir', 'materialise_default_knee']
