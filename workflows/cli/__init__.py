"""The ``pbmdem`` command line (:mod:`workflows.cli.main`): the only layer that prints
errors and sets exit codes. Nothing else imports it."""
