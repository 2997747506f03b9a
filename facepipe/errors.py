"""Errors the user can fix: the CLI turns them into a message and exit status 2."""

import errno

#: Write errors that concern a folder's disk, not the file: a full disk, a quota, a file too large.
DISK_FULL = {errno.ENOSPC, errno.EFBIG} | ({errno.EDQUOT} if hasattr(errno, "EDQUOT") else set())


class InputError(Exception):
    """Bad input: the message names the file, line/frame, marker or vertex, and the fix."""

    def __init__(self, message: str, *, path=None, hint: str | None = None):
        self.path = None if path is None else str(path)
        self.hint = hint
        text = message if self.path is None else f"{self.path}: {message}"
        if hint:
            text = f"{text}\n  hint: {hint}"
        super().__init__(text)


def describe_system_error(exc: BaseException) -> str:
    """What to tell the user of a failure of the machine rather than of facepipe or its input —
    a full disk, a folder it may not write, a path that does not exist, too little memory — as
    ``message\\n  hint: ...`` (no traceback: there is no bug to report)."""

    if isinstance(exc, MemoryError):
        return ("not enough memory\n  hint: close other programs, replay part of the take (--frames), or run on a "
                "machine with more memory")
    code = getattr(exc, "errno", None)
    where = " and ".join(str(p) for p in (getattr(exc, "filename", None), getattr(exc, "filename2", None))
                         if p is not None)
    reason = getattr(exc, "strerror", None) or str(exc)
    text = f"{where}: {reason}" if where else reason
    if code in DISK_FULL:
        hint = ("free space on that disk, or write the outputs elsewhere (-o); complete output files are kept, "
                "partial ones removed")
    elif code in (errno.EACCES, errno.EPERM, errno.EROFS):
        hint = "write somewhere you are allowed to (-o), or check the folder's permissions"
    elif code in (errno.ENOENT, errno.ENOTDIR):
        hint = "check the path (an output folder's parent must exist or be creatable)"
    else:
        hint = "check the disk and the paths given; complete output files are kept, partial ones removed"
    return f"{text}\n  hint: {hint}"
