"""The command line's error policy: exit codes, one-line messages that name the file and the
flag to change, warnings on one line, tracebacks only with `--debug`.

Every command runs through [`run_command`][]. The library raises [`DataError`][] for input
that cannot be used and [`OutputError`][] for an output that cannot be written; where the
way past an error is an argument (`overwrite=True`), the message here shows the command's
flag instead (`--overwrite`).
"""

import argparse
import errno
import os
import signal
import sys
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path

from .._fileio import DataError, DataWarning, OUTPUT_ERRNOS, OutputError


# Exit codes, documented in docs/errors.md.
EXIT_OK = 0
EXIT_INTERNAL = 1  # a bug: please report it with the output of --debug
EXIT_USAGE = 2  # a flag is missing, unknown or has a value that cannot be right (argparse's own code)
EXIT_DATA = 3  # an input file, folder, video or frame cannot be used
EXIT_OUTPUT = 4  # an output cannot be written: read-only, a folder where a file goes, a full disk, a conflict
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM (128 + SIGINT)

EXIT_CODES = {
    EXIT_OK: "success (warnings, if any, were printed)",
    EXIT_INTERNAL: "internal error: a bug in moirejax; rerun with --debug and report the traceback",
    EXIT_USAGE: "usage: a flag is missing, unknown, or has a value that cannot be right",
    EXIT_DATA: "bad input: a file, folder, video or frame named on the command line cannot be used",
    EXIT_OUTPUT: "unwritable output: read-only folder, a folder where a file goes (or the reverse), full disk, "
    "or an existing output that needs --overwrite",
    EXIT_INTERRUPTED: "interrupted by Ctrl-C or SIGTERM; outputs not yet complete were not written",
}

# Python arguments the library names in its messages, and the flags that set them.
FLAGS = {
    "out": "--out",
    "out_dir": "--out",
    "out_csv": "--out",
    "skip_bad": "--skip-bad",
    "overwrite": "--overwrite",
    "force": "--force",
    "reference": "--reference",
    "write": "--write",
    "plot": "--plot",
    "observability_plot": "--observability-plot",
    "record": "--record",
    "sink": "--sink",
    "restore": "--restore",
    "mcap": "--mcap",
}

# The flags of each command that name outputs; the others that name paths are inputs.
OUTPUT_FLAGS = {
    "design": ("write", "plot", "observability_plot"),
    "simulate": ("out",),
    "import": ("out",),
    "invert": ("out", "mcap"),
    "calibrate": ("out",),
    "evaluate": ("out",),
    "transfer": ("out",),
    "live": ("record", "record_frames", "rerun_save", "sink", "mcap"),
    "vision": ("restore",),
    "cap-removal": ("out",),
    "demo": ("out",),
}


def _path_flags(args: argparse.Namespace) -> dict[str, str]:
    """`{path value: flag}` for every option of the command given as a string."""
    flags: dict[str, str] = {}
    for dest, value in vars(args).items():
        values = value if isinstance(value, list) else [value]
        for v in values:
            if isinstance(v, str) and v and dest not in ("command", "preset", "recipe", "protocol", "fidelity"):
                flags[v] = "--" + dest.rstrip("_").replace("_", "-")
    return flags


def _flag_for_path(path: str, args: argparse.Namespace) -> tuple[str | None, bool]:
    """The flag whose value `path` is, lies in, or derives from (`fit.json` -> `fit_report/`),
    and whether that flag names an output."""
    outputs = {"--" + d.replace("_", "-") for d in OUTPUT_FLAGS.get(args.command, ())}
    target = Path(os.path.abspath(path))
    best: tuple[int, str] | None = None
    for value, flag in _path_flags(args).items():
        given = Path(os.path.abspath(value))
        stem = given.with_suffix("")
        if target == given:
            score = 4
        elif given in target.parents:
            score = 3
        elif target.parent == given.parent and target.name.startswith(stem.name):
            score = 2
        else:
            continue
        if best is None or score > best[0]:
            best = (score, flag)
    if best is None:
        return None, False
    return best[1], best[1] in outputs


def _message_with_flag(message: str, args: argparse.Namespace) -> str:
    """A message that names a file given on the command line, with that file's flag added."""
    path = message.split(": ", 1)[0]
    if not path or "\n" in path:
        return message
    flag, _ = _flag_for_path(path, args)
    if flag is None or flag in message:
        return message
    first, _, rest = message.partition("\n")
    return f"{first} (given by {flag})" + (f"\n{rest}" if rest else "")


def _classify_os_error(e: OSError, args: argparse.Namespace) -> tuple[int, str]:
    if isinstance(e, OutputError):
        message = e.for_command_line(FLAGS)
        return EXIT_OUTPUT, _message_with_flag(message, args) if e.argument is None else message
    reason = e.strerror or str(e)
    path = e.filename if isinstance(e.filename, str) else None
    if path is None:
        code = EXIT_OUTPUT if e.errno in OUTPUT_ERRNOS else EXIT_DATA
        return code, reason
    flag, is_output = _flag_for_path(path, args)
    if is_output or (flag is None and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EISDIR)):
        change = f"; change {flag}" if flag else ""
        return EXIT_OUTPUT, f"{path}: cannot be written ({reason}){change}"
    check = f"; check {flag}" if flag else ""
    return EXIT_DATA, f"{path}: cannot be read ({reason}){check}"


# The `source` the commands give a device they build from flags.
COMMAND_LINE = "command line"


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that staged outputs are cleaned up on the way out."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def _one_line_warnings(command: str) -> Callable:
    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message).replace("\n", " ")
        print(f"moirejax {command}: warning: {text}", file=sys.stderr)

    return show


def classify(e: BaseException, args: argparse.Namespace) -> tuple[int, str]:
    """The exit status and the one-line message (after `moirejax COMMAND: `) for `e`."""
    if isinstance(e, KeyboardInterrupt):
        what = "terminated (SIGTERM)" if isinstance(e, _Terminated) else "interrupted"
        return EXIT_INTERRUPTED, f"{what}; outputs not yet complete were not written"
    if isinstance(e, DataError) and str(e).startswith(COMMAND_LINE + ":"):
        # A device built from the command's own flags (`design --p1 ...`) that cannot be.
        return EXIT_USAGE, f"error: {e}"
    if isinstance(e, DataError):
        message = e.for_command_line(FLAGS)
        return EXIT_DATA, "error: " + (_message_with_flag(message, args) if e.argument is None else message)
    if isinstance(e, OSError):
        code, message = _classify_os_error(e, args)
        return code, f"error: {message}"
    if isinstance(e, ValueError):
        # A value the library refused: from a file given on the command line, bad data;
        # else a flag's value.
        text = str(e)
        flagged = _message_with_flag(text, args)
        return (EXIT_DATA if flagged != text else EXIT_USAGE), f"error: {flagged}"
    return EXIT_INTERNAL, f"internal error: {type(e).__name__}: {e}"


def run_command(command: str, run: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run one command under the error policy; returns the exit status.

    Every failure prints one line, `moirejax COMMAND: error: MESSAGE`, naming the file and
    the flag to change (an import's list of bad frames follows it, indented); `--debug`
    prints the traceback before it. Warnings print as `moirejax COMMAND: warning: ...`.
    SIGTERM is handled like Ctrl-C, so an interrupted command cleans up what it staged.
    """
    debug = bool(getattr(args, "debug", False))
    previous = None
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread
        pass
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", DataWarning)
            if not debug:
                warnings.showwarning = _one_line_warnings(command)
            return run(args)
    except (SystemExit, GeneratorExit):
        raise
    except BaseException as e:
        code, message = classify(e, args)
        if debug:
            traceback.print_exception(e)
        elif code == EXIT_INTERNAL:
            message += " (rerun with --debug for the traceback)"
        print(f"moirejax {command}: {message}", file=sys.stderr)
        return code
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
