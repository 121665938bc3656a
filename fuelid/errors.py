"""The one exception the CLI turns into a one-line message on stderr and a non-zero exit."""


class FuelidError(Exception):
    """A user-facing error: bad input, a missing file, a malformed model. The message is the whole story."""
