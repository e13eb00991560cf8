"""The error and warning types that the CLI turns into clear messages."""


class WaveforestError(ValueError):
    """Bad input: the message names the file or field and what was expected."""


class WaveforestWarning(UserWarning):
    """Input that is read on, with a caveat the user should see (file, field, what happened)."""
