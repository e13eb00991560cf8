"""The error type that the CLI turns into one clear message and a non-zero exit."""


class WaveforestError(ValueError):
    """Bad input: the message names the file or field and what was expected."""
