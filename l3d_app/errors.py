"""User-facing errors.

A :class:`UserError` is a problem with the user's input (a missing file, a malformed
mesh, an unknown registry name, a bad size). The app entry prints its message on one
line and exits with status 2, without a traceback.
"""


class UserError(ValueError):
    """Bad input from the user: reported as one line, exit code 2."""


def require(condition: bool, message: str) -> None:
    """Raise :class:`UserError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise UserError(message)
