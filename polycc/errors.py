"""User-facing errors.

A :class:`PolyccError` carries one line that names the file, says what is wrong and
how to fix it. The CLI prints it and exits with code 2; it never shows a traceback.
"""


class PolyccError(Exception):
    """An error caused by the user's input or environment (exit code 2)."""

    exit_code = 2
