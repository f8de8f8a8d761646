"""Configuration: the OmegaConf resolvers posediff's Hydra configs use (:mod:`.resolvers`) and what a
configuration read from a file may build (:mod:`.allowlist`, with the table of classes that moved)."""

from .allowlist import (
    BUILDABLE,
    RENAMED,
    UntrustedConfigError,
    allow_target,
    buildable_targets,
    check_config,
    target_class,
    upgrade_config,
)
from .resolvers import new_run_id, register_resolvers

__all__ = [
    "BUILDABLE",
    "RENAMED",
    "UntrustedConfigError",
    "allow_target",
    "buildable_targets",
    "check_config",
    "new_run_id",
    "register_resolvers",
    "target_class",
    "upgrade_config",
]
