"""The one exception family the CLI turns into a one-line message on stderr and a non-zero exit.

Every error a user can cause (bad input, a missing or malformed file, data that cannot give the result asked
for) is a FuelidError; code that handles such errors catches FuelidError, never ValueError next to it.
ValueError and TypeError stay what they are in Python: a caller passed arguments that make no sense.
"""


class FuelidError(Exception):
    """A user-facing error: bad input, a missing file, a malformed model. The message is the whole story."""


class InputError(FuelidError, ValueError):
    """Input that fuelid cannot use: an option or setting out of its range, a malformed spec, data that cannot
    give the result asked for (too few valid samples, nothing to calibrate on). Also a ValueError, what Python
    raises for a bad value, so callers that checked for that keep working."""
