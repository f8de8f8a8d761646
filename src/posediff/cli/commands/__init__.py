"""One module per ``posediff`` command, each with ``run(cfg) -> int`` (its exit code), read top to bottom:
check the options, build from config, do the work, write the outputs. Input errors are raised (as
:class:`~posediff.cli.errors.InputError` or posediff's own error classes) and become one line in
:func:`~posediff.cli.errors.reports_input_errors`, which :mod:`posediff.cli.main` puts around
every command."""
