"""The one exception type for user mistakes.

Everything a user can get wrong (a missing file, an impossible lens, a malformed PLY) raises
:class:`DofsplatError`. It subclasses ``ValueError`` so that library callers can catch it
with the usual idiom; the CLI turns it into one line on stderr and exit status 2.
"""


class DofsplatError(ValueError):
    """A user-facing error: bad input, bad settings, unreadable file."""
