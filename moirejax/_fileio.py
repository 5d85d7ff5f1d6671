"""Atomic file writes, output checks, staged sets of outputs, and JSON-Schema validation for
every file moirejax reads or writes; the exceptions and warning that name a bad file."""

import contextlib
import errno
import functools
import hashlib
import importlib.resources
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import jax
import jsonschema
import numpy as np


# The process umask, read once: os.umask can only be read by setting it.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


# Where a message names the argument that gets past it, this placeholder stands for it.
ARGUMENT = "{argument}"


class _NamesAnArgument:
    """An error whose message may name the argument a user changes to get past it.

    From Python the argument reads as a keyword (`overwrite=True`); a command line shows
    its own flag instead (`--overwrite`) through `for_command_line`.
    """

    template: str
    argument: str | None
    python: str

    def _render(self, name: str) -> str:
        return self.template.replace(ARGUMENT, name)

    def for_command_line(self, flags: Mapping[str, str] | None = None) -> str:
        """The message with the argument shown as a command-line flag: `flags[argument]`,
        or `--` and the argument with dashes (`skip_bad` -> `--skip-bad`)."""
        if self.argument is None:
            return self._render("")
        flag = (flags or {}).get(self.argument) or "--" + self.argument.replace("_", "-")
        return self._render(flag)


class DataError(_NamesAnArgument, ValueError):
    """A file does not match what moirejax expects. The message names the file and field.

    **Arguments:**

    - `message`: what is wrong, naming the file; an `{argument}` in it stands for
      the argument that gets past the error.
    - `argument`: that argument's keyword name (`"overwrite"`, `"skip_bad"`), if any.
    - `python`: how the argument reads from Python (default `NAME=True`).
    """

    def __init__(self, message: str, *, argument: str | None = None, python: str | None = None):
        self.template, self.argument = message, argument
        self.python = python or (f"{argument}=True" if argument else "")
        super().__init__(self._render(self.python))


class OutputError(_NamesAnArgument, OSError):
    """An output cannot be written where it was asked for: the folder is read-only or
    missing, a file name is a folder (or a folder name a file), the disk is full.

    Raised before any long work where it can be foreseen. `argument` names the argument
    holding the path (`"out"`), which a command line shows as its flag (`--out`). A
    subclass of `OSError`, like the errors of a failed write it stands for.
    """

    def __init__(self, message: str, *, argument: str | None = None, python: str | None = None):
        self.template, self.argument = message, argument
        self.python = python or (argument or "")
        super().__init__(self._render(f"`{self.python}`" if self.python else ""))


class DataWarning(UserWarning):
    """Data was usable but not all of it: a truncated video, a bad reference frame skipped,
    a calibration its frames cannot identify. The message names the file."""


def _nearest_existing(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _probe_folder(folder: Path, what: Path, argument: str | None) -> None:
    """Raise `OutputError` unless a file can be created in `folder` (or the folder made)."""
    base = _nearest_existing(folder)
    if not base.is_dir():
        raise OutputError(
            f"{what}: cannot be created: {base} is a file, not a folder; change {ARGUMENT}", argument=argument
        )
    try:
        fd, probe = tempfile.mkstemp(prefix=".moirejax-probe-", dir=base)
    except OSError as e:
        raise OutputError(
            f"{what}: cannot write in {base} ({e.strerror or e}); change {ARGUMENT} or the folder's permissions",
            argument=argument,
        ) from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path: str | os.PathLike, *, argument: str | None = None) -> Path:
    """Check, before any long work, that a file can be written at `path`: it is not a folder,
    and its folder exists or can be made and is writable. Raises `OutputError`."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a folder; {ARGUMENT} needs a file name", argument=argument)
    _probe_folder(path.parent, path, argument)
    return path


def check_output_folder(path: str | os.PathLike, *, argument: str | None = None) -> Path:
    """Check, before any long work, that `path` can be a folder of outputs: it is not a file,
    and it, or the folder it would be made in, is writable. Raises `OutputError`."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: is a file; {ARGUMENT} needs a folder", argument=argument)
    _probe_folder(path, path, argument)
    return path


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def staging_folder(beside: str | os.PathLike) -> Iterator[Path]:
    """A temporary folder in the folder of `beside` (so that renames out of it stay on one
    filesystem), removed on exit, with whatever is left in it: outputs written there
    and not yet moved out by `commit_staged` vanish if the job fails or is interrupted."""
    parent = Path(os.path.abspath(beside)).parent
    created = _nearest_existing(parent)
    parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{Path(beside).name}.staging-", dir=parent))
    try:
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        # Folders made for the outputs go too, when nothing landed in them.
        folder = parent
        while folder != created and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
            folder = folder.parent


def commit_staged(staging: Path, moves: list[tuple[Path, Path]]) -> None:
    """Move staged files and folders onto their targets, in order: put the one that marks
    the set complete (the manifest) last.

    Everything slow (computing, plotting, writing, flushing to disk) happened while
    staging; this is renames only. A file replaces its target atomically (the old one is
    kept as a hard link in `staging` meanwhile); a folder replaces its target by two
    renames (the old one is moved into `staging`). If any step fails or is interrupted
    (Ctrl-C, SIGTERM), the steps already taken are undone, so the old set is back; only a
    kill that cannot be caught, in the instant between two renames, leaves a mix.
    """
    for source, target in moves:
        if source.is_dir() and target.exists() and not target.is_dir():
            raise OutputError(f"{target}: is a file where a folder of outputs goes")
        if not source.is_dir() and target.is_dir():
            raise OutputError(f"{target}: is a folder where a file goes")
    undo: list[tuple[Path | None, Path]] = []  # (old copy or None, target)
    try:
        for k, (source, target) in enumerate(moves):
            old: Path | None = None
            if target.exists():
                old = staging / f".old-{k}"
                if source.is_dir():
                    os.replace(target, old)
                else:
                    try:
                        os.link(target, old)
                    except OSError:  # a filesystem without hard links
                        shutil.copy2(target, old)
            undo.append((old, target))
            os.replace(source, target)
    except BaseException:
        for old, target in reversed(undo):
            try:
                if old is None:
                    if target.is_dir():
                        shutil.rmtree(target)
                    elif target.exists():
                        target.unlink()
                elif old.exists():
                    if target.is_dir() and old.is_dir():
                        shutil.rmtree(target)
                    os.replace(old, target)
            except OSError:
                pass
        raise
    for folder in {target.parent for _, target in moves}:
        _fsync_folder(folder)


# OSError numbers that mean "this output cannot be written here".
OUTPUT_ERRNOS = frozenset(
    {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.EISDIR, errno.ENOTDIR, errno.EEXIST}
)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` so that readers see either the old file or the whole new one.

    The bytes go to a temporary file in the same directory (so the final rename
    stays on one filesystem), are flushed to disk, and then replace `path`.
    An interrupt before the rename leaves `path` untouched. The file gets the mode a plain
    `open` would give it (an existing file keeps its own), not the temporary's 0600.
    A write that fails (full disk, read-only folder) raises [`OutputError`][] naming `path`.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            mode = path.stat().st_mode & 0o777
        except FileNotFoundError:
            mode = 0o666 & ~_UMASK
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise OutputError(f"{path}: cannot be written ({e.strerror or e})") from e
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        # Also on KeyboardInterrupt: never leave a half-written temporary behind.
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(e, OSError) and not isinstance(e, OutputError):
            # A full disk, a quota, a folder gone read-only: named, and the old file kept.
            raise OutputError(f"{path}: cannot be written ({e.strerror or e}); the previous file is unchanged") from e
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """[`atomic_write_bytes`][] for UTF-8 text."""
    atomic_write_bytes(path, text.encode("utf-8"))


def fingerprint(*trees: Any) -> str:
    """A SHA-256 of the arrays and the structure of pytrees (devices, inverters, frame
    indices): equal for two runs whose work is interchangeable, part for part."""
    digest = hashlib.sha256()
    for tree in trees:
        leaves, structure = jax.tree_util.tree_flatten(tree)
        digest.update(str(structure).encode())
        for leaf in leaves:
            array = np.asarray(leaf)
            digest.update(f"{array.dtype}{array.shape}".encode())
            digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


PLAN_NAME = "plan.json"


def open_parts(parts: Path, plan: dict, *, argument: str, restart_other: bool = False) -> bool:
    """The folder `parts` that keeps the finished parts of a long job beside its output
    (`OUT.parts/`), so that a rerun after an interruption redoes only what is missing.

    `plan` says what the job is (its inputs and settings, as JSON); the folder is made with
    it, or, when it exists, must hold a job of the same plan. Parts of another plan raise
    [`DataError`][], or with `restart_other` are dropped with a [`DataWarning`][] (for a
    job whose rerun with new inputs means to replace them). Returns whether the folder
    already held this plan's parts. Each part is written with [`atomic_write_bytes`][], so
    a part on disk is whole.
    """
    plan_file = parts / PLAN_NAME
    if parts.exists():
        try:
            previous = json.loads(plan_file.read_text())
        except (OSError, ValueError):
            previous = None
        if previous == plan:
            return True
        if not restart_other:
            raise DataError(
                f"{parts}: parts of a different run (other inputs or settings); remove the folder to start afresh"
            )
        warnings.warn(f"{parts}: parts of a different run dropped; this run starts afresh", DataWarning, stacklevel=3)
        try:
            shutil.rmtree(parts)
        except OSError as e:
            raise OutputError(
                f"{parts}: parts of a different run cannot be removed ({e.strerror or e})", argument=argument
            ) from e
    try:
        parts.mkdir(parents=True)
    except OSError as e:
        raise OutputError(f"{parts}: cannot be made ({e.strerror or e})", argument=argument) from e
    atomic_write_text(plan_file, json.dumps(plan, indent=1))
    return False


@functools.cache
def load_schema(name: str) -> dict[str, Any]:
    """Load the package's `data_schema/<name>.schema.json`.

    Read through `importlib.resources`, so it works from a wheel, a zip or a checkout alike.
    """
    schema = importlib.resources.files("moirejax").joinpath("data_schema", f"{name}.schema.json")
    return json.loads(schema.read_text(encoding="utf-8"))


def validate_json(obj: Any, schema_name: str, *, source: str = "<memory>") -> None:
    """Validate `obj` against a schema, raising [`DataError`][] naming the file and field."""
    validator = jsonschema.Draft202012Validator(load_schema(schema_name))
    errors = sorted(validator.iter_errors(obj), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        field = "/".join(str(p) for p in err.absolute_path) or "<root>"
        raise DataError(f"{source}: field '{field}': {err.message}")


def read_json(path: str | os.PathLike, schema_name: str | None = None) -> Any:
    """Read a JSON file, optionally validating it against a named schema."""
    path = Path(path)
    try:
        with open(path, encoding="utf-8") as f:
            obj = json.load(f)
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except json.JSONDecodeError as e:
        raise DataError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror or e})") from None
    if schema_name is not None:
        validate_json(obj, schema_name, source=str(path))
    return obj


def write_json(path: str | os.PathLike, obj: Any, schema_name: str | None = None) -> None:
    """Validate (optionally) and atomically write `obj` as indented JSON."""
    if schema_name is not None:
        validate_json(obj, schema_name, source=str(path))
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")
