"""One error tree for the whole package.

Every error a user can cause derives from :class:`ArchiveError`; the CLI prints its message on one
line and exits non-zero. Specific kinds also derive from the matching built-in so that callers can
catch ``FileNotFoundError`` or ``ValueError`` as usual. Messages name the file (or cube, key, band)
and say what was expected and how to fix it.
"""

from __future__ import annotations

import errno
from os import PathLike


class ArchiveError(Exception):
    """Root of all errors raised on purpose by archive."""

    exit_code = 2


class InputError(ArchiveError, ValueError):
    """An input file or argument has the wrong content."""

    def __init__(self, where: str | PathLike | None, problem: str, fix: str | None = None):
        self.where = None if where is None else str(where)
        self.problem = problem
        self.fix = fix
        text = problem if self.where is None else f"{self.where}: {problem}"
        if fix:
            text += f" ({fix})"
        super().__init__(text)


class FormatError(InputError):
    """A file exists but does not follow its format (header key, column count, size...)."""


class MissingInputError(ArchiveError, FileNotFoundError):
    """A file or directory the user pointed at (or that a flight needs) does not exist."""

    def __init__(self, path: str | PathLike, what: str = "file", fix: str | None = None):
        self.path = str(path)
        text = f"{self.path}: {what} not found"
        if fix:
            text += f" ({fix})"
        super().__init__(text)


class OutputExistsError(ArchiveError, FileExistsError):
    """An output exists already and --overwrite was not given."""

    def __init__(self, path: str | PathLike):
        self.path = str(path)
        super().__init__(f"{self.path}: output exists already (pass --overwrite to replace it)")


class NavigationError(InputError):
    """Navigation does not cover, or cannot be aligned with, the image lines."""


class NoLineOnGrid(InputError):
    """The requested grid (``--bounds``, ``--like``, a stack's) holds no line of the flights: a stack or a
    tile leaves such a flight out, a single render refuses."""


class RenderError(ArchiveError, RuntimeError):
    """The OpenGL renderer could not start or failed."""


#: errno -> (what the file system said, the fix), for :func:`file_system_refusal`.
_REFUSALS = {
    errno.EROFS: ("the file system is read-only", "run it where the archive or output is writable, or choose "
                  "another output folder"),
    errno.EACCES: ("permission denied", "run it as a user who may write there, or choose another folder"),
    errno.EPERM: ("operation not permitted", "run it as a user who may write there, or choose another folder"),
    errno.ENOSPC: ("no space left on the device", "free some space there (or choose another folder), then run "
                   "it again"),
    errno.EDQUOT: ("the disk quota is exceeded", "free some space there (or choose another folder), then run "
                   "it again"),
}


def file_system_refusal(exc: OSError) -> str | None:
    """The one line for an OSError of a full, read-only or forbidden file system (naming its path), else None."""
    known = _REFUSALS.get(exc.errno)
    if known is None:
        return None
    where = exc.filename if exc.filename is not None else "a file"
    return f"{where}: {known[0]} ({known[1]})"



def warning_lines(command: str) -> None:
    """Show this package's warnings as one clean line each on stderr, ``archive COMMAND: warning: ...``
    (above a progress bar, never glued to it: through tqdm when it is loaded); other libraries' warnings
    keep Python's format."""
    import sys
    import warnings

    default = warnings.showwarning
    package = __file__.rsplit("/", 1)[0]

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if not str(filename).startswith(package):
            return default(message, category, filename, lineno, file, line)
        text = f"archive {command}: warning: {' '.join(str(message).split())}"
        tqdm = sys.modules.get("tqdm")
        if tqdm is not None:
            tqdm.tqdm.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr)

    warnings.showwarning = show
