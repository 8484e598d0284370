"""The one error type of the package: every failure the command line reports as a one-line
message with a non-zero exit status."""


class UsdToolError(Exception):
    """A failure caused by the input (missing file, bad manifest, unresolvable prototype)."""
