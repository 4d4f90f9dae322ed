"""The one exception type for user mistakes.

Everything a user can get wrong (a missing file, an impossible lens, a malformed PLY) raises
:class:`DofsplatError`. It subclasses ``ValueError`` so that library callers can catch it
with the usual idiom; the CLI turns it into one line on stderr and exit status 2.
:func:`library_message` quotes a library's exception inside such a message.
"""

LIBRARY_MESSAGE_CHARS = 300  # a library's message past this is cut, at a word


class DofsplatError(ValueError):
    """A user-facing error: bad input, bad settings, unreadable file."""


def library_message(e: BaseException) -> str:
    """A library's exception as the end of a DofsplatError's message: ``TypeName: text``.

    The text is the exception's first non-empty line: libE57Format follows its message
    ("checksum mismatch, file is corrupted (ErrorBadChecksum)") with the same message again,
    a debug context and source locations over eight more lines, which the CLI's one line
    would have shown run together. A first line longer than ``LIBRARY_MESSAGE_CHARS`` (a
    library that quotes a whole array) is cut at a space, with "...".
    """
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    text = " ".join(lines[0].split()) if lines else "no details"
    if len(text) > LIBRARY_MESSAGE_CHARS:
        text = text[:LIBRARY_MESSAGE_CHARS].rsplit(" ", 1)[0] + " ..."
    return f"{type(e).__name__}: {text}"
