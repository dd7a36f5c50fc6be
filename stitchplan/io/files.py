"""Writers for results: CSV, JSON, YAML and HDF5, each written atomically.

A file a robot or a script may pick up is written to a temporary file in the same folder
and renamed into place, so a failed run never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError


def check_output_paths(*paths: str | Path | None) -> None:
    """Refuse, before any work, an output that cannot be written: a file standing where a
    folder must be, a folder given as the file name, a folder without write permission."""
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        if path.is_dir():
            raise InputError(f"{path}: is a folder, expected a file name")
        for parent in path.resolve().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise InputError(f"{path}: cannot write, {parent} is not a folder")
                if not os.access(parent, os.W_OK | os.X_OK):
                    raise InputError(f"{path}: cannot write, no permission to write in {parent}")
                break


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yields a temporary path next to `path`; renames it onto `path` if the block succeeds."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or ".tmp",
                                             dir=path.parent)
    except OSError as error:
        raise InputError(f"{path}: cannot write ({error.strerror or error})") from None
    os.close(handle)
    try:
        yield Path(temporary)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # mkstemp creates 0600; give the usual file mode
        os.replace(temporary, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as temporary:
        temporary.write_text(text)


def write_csv(path: str | Path, columns: Sequence[str], rows: np.ndarray | Sequence[Sequence[Any]],
              precision: int = 9) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_format(value, precision) for value in row])
    write_text(path, buffer.getvalue())


def _format(value: Any, precision: int) -> Any:
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.{precision}g}"
    if isinstance(value, np.integer):
        return int(value)
    return value


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def write_json(path: str | Path, data: dict) -> None:
    write_text(path, json.dumps(_plain(data), indent=2) + "\n")


def write_yaml(path: str | Path, data: dict, header: str = "") -> None:
    import yaml

    write_text(path, header + yaml.safe_dump(_plain(data), sort_keys=False))


def write_hdf5(path: str | Path, groups: dict[str, dict[str, Any]], attributes: dict[str, Any]) -> None:
    """groups: {"group/sub": {"dataset": array, ...}}; attributes go on the root."""
    import h5py

    with atomic_path(path, suffix=".h5") as temporary, h5py.File(temporary, "w") as handle:
        for key, value in attributes.items():
            handle.attrs[key] = _attribute(value)
        for group_name, datasets in groups.items():
            group = handle.require_group(group_name)
            for name, value in datasets.items():
                if isinstance(value, str):
                    group.create_dataset(name, data=value, dtype=h5py.string_dtype())
                else:
                    data = np.asarray(value)
                    options = {"compression": "gzip", "compression_opts": 4} if data.size > 1000 else {}
                    group.create_dataset(name, data=data, **options)


def _attribute(value: Any) -> Any:
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(_plain(value))
    return value
