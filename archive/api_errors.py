"""Errors of the Python API in the words of the caller: the function and keyword the user passed,
not the command line's flags (``--ground-height``) nor an inner constructor
(``RenderOptions.create()``).

The library shares its checks with ``archive render``, whose messages name CLI options; a call of
:func:`archive.mosaic` (or ``georectify``, ``stack``, ``plan``, ``Archive.search``) goes through
:func:`python_errors`, which rewrites the option names of an :class:`~archive.errors.InputError`
into keywords (``--ground-height 80`` -> ``ground_height=80``) and makes an unknown keyword one
line naming the function, the keyword and the nearest valid one.
"""

from __future__ import annotations

import contextlib
import difflib
import functools
import re
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

from archive.errors import ArchiveError, InputError, OutputExistsError

__all__ = ["KeywordError", "keep_cli_flags", "python_errors", "python_words", "unknown_keyword"]

F = TypeVar("F", bound=Callable)

#: Flags that are switches: in Python they are ``name=True``.
_SWITCHES = {"overwrite", "resume", "align", "provenance", "quiet", "stack", "apply"}

#: ``--flag`` with an optional value in capitals (FILE, DEG, W,S,E,N) or a number after it.
_FLAG = re.compile(r"--([a-z][a-z0-9-]*)(?: ([A-Z][A-Z0-9,._]*\b|-?\d[\d.,]*\d|\d))?")


#: Set by the command line (:func:`keep_cli_flags`): its messages name the flags the user typed.
_CLI = {"flags": False}


@contextlib.contextmanager
def keep_cli_flags() -> Iterator[None]:
    """Inside it, messages stay in the command line's words (``archive ...`` calls the same API
    functions as Python users)."""
    before, _CLI["flags"] = _CLI["flags"], True
    try:
        yield
    finally:
        _CLI["flags"] = before


class KeywordError(ArchiveError, TypeError):
    """A keyword the called function does not take (a ``TypeError``, as Python's own)."""


def python_words(text: str | None) -> str | None:
    """``text`` with CLI flags written as Python keywords: ``--fov DEG`` -> ``fov=DEG``,
    ``--overwrite`` -> ``overwrite=True``, ``--bounds`` -> ``bounds``."""
    if text is None:
        return None

    def keyword(match: re.Match) -> str:
        name, value = match.group(1).replace("-", "_"), match.group(2)
        if value is not None:
            return f"{name}={value}"
        return f"{name}=True" if name in _SWITCHES else name

    return _FLAG.sub(keyword, text)


def unknown_keyword(function: str, error: TypeError, given: Iterable[str], valid: Iterable[str]) -> Exception:
    """A :class:`KeywordError` for Python's "got an unexpected keyword argument 'x'" when ``x`` is
    one of the keywords the caller gave (``given``) and not one of ``valid``; else ``error`` itself."""
    match = re.search(r"unexpected keyword argument '([^']+)'", str(error))
    names = sorted(valid)
    if match is None or match.group(1) not in given or match.group(1) in names:
        return error
    name = match.group(1)
    near = difflib.get_close_matches(name, names, n=1)
    fix = f"did you mean {near[0]}=?" if near else f"its keywords: {', '.join(names)}"
    return KeywordError(f"{function}(): no keyword {name!r} ({fix})")


def python_errors(function: str, valid: Callable[[], Iterable[str]]) -> Callable[[F], F]:
    """Decorator of a public API function named ``function`` (``'archive.mosaic'``): an InputError
    naming a CLI option names the keyword and the function instead; an unexpected keyword
    (``valid()``: the keywords it takes) is a :class:`KeywordError` naming ``function``."""

    def decorate(func: F) -> F:
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            try:
                return func(*args, **kwargs)
            except InputError as exc:
                if not _CLI["flags"]:   # "pass --overwrite" is "pass overwrite=True" in Python
                    if exc.where is not None and exc.where.startswith("--"):
                        keyword = python_words(exc.where.split()[0])
                        exc.where = f"{function}({keyword.split('=')[0]}=...)"
                    exc.problem, exc.fix = python_words(exc.problem), python_words(exc.fix)
                    text = (f"{exc.where}: " if exc.where is not None else "") + f"{exc.problem}" + \
                        (f" ({exc.fix})" if exc.fix else "")
                    exc.args = (text,)
                raise
            except OutputExistsError as exc:
                if not _CLI["flags"]:
                    exc.args = (python_words(str(exc)),)
                raise
            except TypeError as exc:
                if isinstance(exc, ArchiveError):
                    raise
                raised = unknown_keyword(function, exc, kwargs, valid())
                if raised is exc:
                    raise
                raise raised from None

        return wrapper  # type: ignore[return-value]

    return decorate
