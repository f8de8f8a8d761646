"""The ``posediff`` command line: :mod:`.main` (the command table and dispatch over Hydra), :mod:`.errors`
(input errors → one line, exit 2), :mod:`.commands` (one module per command)."""

from .main import (
    COMMANDS,
    DATA_COMMANDS,
    PATH_KEYS,
    Command,
    _unknown_config_choice,
    config_dir,
    entrypoint,
    input_error_line,
    main,
    prepare_args,
    usage,
)

__all__ = ["COMMANDS", "DATA_COMMANDS", "PATH_KEYS", "Command", "_unknown_config_choice", "config_dir",
           "entrypoint", "input_error_line", "main", "prepare_args", "usage"]  # fmt: skip
