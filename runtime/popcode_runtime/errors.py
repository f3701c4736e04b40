"""The one exception type the runtime raises for bad input or bad models."""


class PopcodeError(ValueError):
    """Bad input, a bad model file or inconsistent metadata; the message says which.

    The command line prints the message as one line and exits non-zero.
    """
