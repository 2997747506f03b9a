"""Errors the user can fix: the CLI turns them into a message and exit status 2."""


class InputError(Exception):
    """Bad input: the message names the file, line/frame, marker or vertex, and the fix."""

    def __init__(self, message: str, *, path=None, hint: str | None = None):
        self.path = None if path is None else str(path)
        self.hint = hint
        text = message if self.path is None else f"{self.path}: {message}"
        if hint:
            text = f"{text}\n  hint: {hint}"
        super().__init__(text)
