"""Sub-commands of the `sav-jax` command line (one module each).

Each module defines `HELP` (one line), `add_arguments(parser)` and `run(args) -> int`.
Heavy imports (jax, the model) happen inside `run`, so `sav-jax --help` is instant.
A `UsageError` (or ValueError / FileNotFoundError / FileExistsError) raised by
`run` is printed as one clean line and exits with status 2.
"""


class UsageError(Exception):
  """Bad input from the user: reported without a traceback, exit status 2."""
