"""The error contract shared by the four command-line programs.

``calendaring``, ``surrogate``, ``inverse`` and ``analysis`` end every invocation with one
of these exit codes:

- 0: success;
- 2: a user error (a missing or unreadable input, an output path that cannot be written,
  an invalid value of any key or option, a wrong kind of file, options that contradict
  each other, a disk that is full): one line on stderr naming the thing, the value and
  what is allowed, and no output or temporary file left behind;
- 3: a simulation stopped on one of its guards (NaN, runaway overlap, a particle leaving
  the cell, a full pool): the diagnostic, with the last checkpoint kept;
- 1: an internal error, i.e. a bug: the traceback and a line saying so;
- 130: interrupted (Ctrl-C).

:func:`run_cli` enforces it at each program's entry point, so a handler only raises:
:class:`~calendaring.core.errors.ConfigError` or :class:`UserInputError` for what the user can
fix (each package adds its own error types, e.g. a corrupt run file), and
:class:`~calendaring.core.errors.SimulationError` for a guard. File-system errors
(:class:`OSError` with a file-system errno) are user errors too. Anything else is a bug.

:class:`ContractParser` gives argparse's own errors the same one-line form, and
:func:`integer` / :func:`real` are argparse types that check ranges and reject NaN and
infinities while parsing. :func:`input_file` and :func:`output_path` check paths before any
work starts.

See also: :mod:`calendaring.core.errors` (the error types behind codes 2 and 3),
:mod:`calendaring.cli` (the ``calendaring`` program).
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import sys
import tempfile
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path

from calendaring.core.errors import ConfigError, SimulationError

EXIT_OK, EXIT_BUG, EXIT_BAD_INPUT, EXIT_UNSTABLE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130

#: errno values of an OSError that the user (or the machine's state) caused, not the code
USER_ERRNOS = frozenset({errno.ENOENT, errno.EACCES, errno.EPERM, errno.EISDIR,
                         errno.ENOTDIR, errno.ENOSPC, errno.EROFS, errno.EDQUOT,
                         errno.EEXIST, errno.ENAMETOOLONG, errno.EFBIG, errno.ELOOP,
                         errno.ENOTEMPTY, errno.EXDEV, errno.EBUSY, errno.ETXTBSY})


class UserInputError(ValueError):
    """A problem the user can fix that is not one configuration key: a path, a file of the
    wrong kind, options that contradict each other.

    Args:
        thing: what is wrong, e.g. ``--out`` or ``target file``.
        value: the offending value.
        allowed: what would be accepted.
    """

    def __init__(self, thing: str, value: object, allowed: str) -> None:
        self.thing, self.value, self.allowed = thing, value, allowed
        super().__init__(f"{thing} = {value!r} is invalid: allowed {allowed}")


class ContractParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line and exit 2 (see the module)."""

    def error(self, message: str):
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)


def _num(v) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


def _range_text(lo, hi, lo_open: bool, hi_open: bool, unit: str) -> str:
    u = f" {unit}" if unit else ""
    if lo is not None and hi is not None:
        return (f"in {'(' if lo_open else '['}{_num(lo)}, {_num(hi)}"
                f"{')' if hi_open else ']'}{u}")
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_num(lo)}{u}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {_num(hi)}{u}"
    return "any value"


def integer(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``[lo, hi]`` (either bound optional)."""

    def parse(text: str) -> int:
        bounds = _range_text(lo, hi, False, False, "")
        allowed = "an integer" + ("" if bounds == "any value" else f" {bounds}")
        try:
            v = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is invalid: allowed {allowed}") from None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{v} is invalid: allowed {allowed}")
        return v

    parse.__name__ = "integer"
    return parse


def real(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
         hi_open: bool = False, unit: str = "") -> Callable[[str], float]:
    """An argparse ``type``: a finite number within the bounds (open or closed)."""

    def parse(text: str) -> float:
        allowed = f"a finite number {_range_text(lo, hi, lo_open, hi_open, unit)}"
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is invalid: allowed {allowed}") from None
        bad = not math.isfinite(v)
        bad |= lo is not None and (v <= lo if lo_open else v < lo)
        bad |= hi is not None and (v >= hi if hi_open else v > hi)
        if bad:
            raise argparse.ArgumentTypeError(f"{v:g} is invalid: allowed {allowed}")
        return v

    parse.__name__ = "number"
    return parse


def input_file(path: str | Path, thing: str, suffixes: Iterable[str] = ()) -> Path:
    """``path`` as an existing, readable file (with one of ``suffixes`` if given)."""
    p = Path(path)
    suffixes = tuple(s.lower() for s in suffixes)
    if not p.exists():
        raise UserInputError(thing, str(p), "an existing file (there is none)")
    if p.is_dir():
        raise UserInputError(thing, str(p), "a file (it is a folder)")
    if not os.access(p, os.R_OK):
        raise UserInputError(thing, str(p), "a readable file (permission denied)")
    if suffixes and p.suffix.lower() not in suffixes:
        raise UserInputError(thing, str(p), f"a file ending in {' or '.join(suffixes)}")
    return p


def input_folder(path: str | Path, thing: str) -> Path:
    """``path`` as an existing, readable folder."""
    p = Path(path)
    if not p.is_dir():
        why = "it is a file" if p.exists() else "there is none"
        raise UserInputError(thing, str(p), f"an existing folder ({why})")
    if not os.access(p, os.R_OK | os.X_OK):
        raise UserInputError(thing, str(p), "a readable folder (permission denied)")
    return p


def _writable_ancestor(p: Path) -> tuple[Path, str | None]:
    """The nearest existing ancestor of ``p`` and why files cannot be made under it (a
    probe file is created and removed there: permission bits alone do not tell, e.g. for
    root, a read-only mount or a pseudo file system)."""
    q = p.absolute()
    while not q.exists():
        if q.parent == q:
            break
        q = q.parent
    if not q.is_dir():
        return q, f"{q} is a file, not a folder"
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=q)
    except OSError as err:
        return q, f"{q}: {err.strerror or err}"
    os.close(fd)
    os.unlink(probe)
    return q, None


def output_path(path: str | Path, thing: str, *, suffixes: Iterable[str] = (),
                overwrite: bool = False, folder: bool = False) -> Path:
    """Check, before any work, that ``path`` can be written: the nearest existing folder
    above it is writable, it has one of ``suffixes``, and it does not exist unless
    ``overwrite``. With ``folder``, ``path`` is an output folder (it may exist). Creates
    nothing."""
    p = Path(path)
    suffixes = tuple(s.lower() for s in suffixes)
    if folder:
        if p.exists() and not p.is_dir():
            raise UserInputError(thing, str(p), "a folder (it is a file)")
        target = p
    else:
        if suffixes and p.suffix.lower() not in suffixes:
            raise UserInputError(thing, str(p), f"a path ending in {' or '.join(suffixes)}")
        if p.is_dir():
            raise UserInputError(thing, str(p), "a file path, not a folder")
        if p.exists() and not overwrite:
            raise UserInputError(thing, str(p), "a new file (it exists; pass --overwrite)")
        target = p.parent
    _, why = _writable_ancestor(target if target != Path("") else Path("."))
    if why is not None:
        raise UserInputError(thing, str(p), f"a path that can be written ({why})")
    return p


def describe_os_error(err: OSError) -> str:
    """One line for a file-system error: the path(s), the reason."""
    what = err.strerror or type(err).__name__
    paths = [str(f) for f in (err.filename, err.filename2) if f]
    if not paths:
        return f"{what} ({err})" if str(err) and str(err) != what else what
    return f"{' -> '.join(paths)}: {what}"


def one_line(text: str, limit: int = 600) -> str:
    """``text`` on one line (whitespace runs collapsed), cut to ``limit`` characters: a
    library's multi-line message (torch's unpickler, h5py) stays one contract line."""
    flat = " ".join(text.split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def is_user_os_error(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in USER_ERRNOS


def run_cli(prog: str, handler: Callable[[], int], user_errors: tuple = (),
            version: str = "") -> int:
    """Call ``handler`` and map what it raises to the contract's exit codes.

    ``handler`` parses the command line itself, so that argparse's exits (usage errors 2,
    ``--help`` 0) come back here as return codes too.
    """
    try:
        return handler()
    except SystemExit as exc:
        return int(exc.code) if isinstance(exc.code, int) else EXIT_BAD_INPUT
    except (ConfigError, UserInputError, *user_errors) as err:
        print(f"{prog}: error: {one_line(str(err))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except SimulationError as err:
        print(f"{prog}: simulation stopped: {one_line(str(err), 2000)}", file=sys.stderr)
        return EXIT_UNSTABLE
    except OSError as err:
        if not is_user_os_error(err):
            return _bug(prog, version)
        print(f"{prog}: error: {one_line(describe_os_error(err))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception:
        return _bug(prog, version)


def _bug(prog: str, version: str) -> int:
    traceback.print_exc()
    v = f" {version}" if version else ""
    print(f"{prog}: internal error: this is a bug in {prog}{v}; please report it with the "
          "command line and the traceback above", file=sys.stderr)
    return EXIT_BUG


__all__ = ["EXIT_BAD_INPUT", "EXIT_BUG", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_UNSTABLE",
           "ContractParser", "UserInputError", "describe_os_error", "input_file",
           "input_folder", "integer", "is_user_os_error", "one_line", "output_path", "real",
           "run_cli"]
