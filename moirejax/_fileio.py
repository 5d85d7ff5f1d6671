"""Atomic file writes and JSON-Schema validation for every file moirejax reads or writes."""

import functools
import importlib.resources
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import jsonschema


# The process umask, read once: os.umask can only be read by setting it.
_UMASK = os.umask(0o022)
os.umask(_UMASK)


class DataError(ValueError):
    """A file does not match what moirejax expects. The message names the file and field."""


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` so that readers see either the old file or the whole new one.

    The bytes go to a temporary file in the same directory (so the final rename
    stays on one filesystem), are flushed to disk, and then replace `path`.
    An interrupt before the rename leaves `path` untouched. The file gets the mode a plain
    `open` would give it (an existing file keeps its own), not the temporary's 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        mode = path.stat().st_mode & 0o777
    except FileNotFoundError:
        mode = 0o666 & ~_UMASK
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        # Also on KeyboardInterrupt: never leave a half-written temporary behind.
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """[`atomic_write_bytes`][] for UTF-8 text."""
    atomic_write_bytes(path, text.encode("utf-8"))


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
    if schema_name is not None:
        validate_json(obj, schema_name, source=str(path))
    return obj


def write_json(path: str | os.PathLike, obj: Any, schema_name: str | None = None) -> None:
    """Validate (optionally) and atomically write `obj` as indented JSON."""
    if schema_name is not None:
        validate_json(obj, schema_name, source=str(path))
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")
