"""Writing results: every command's outputs as one all-or-nothing set, and the writers of
CSV, JSON, YAML and HDF5.

`OutputSet` is the transaction of one command. Before the run, `check()` makes sure every
output can be created (its folder exists or can be made and takes new files, the target is
not a folder or a device, an existing target may be written) and that no two outputs, and no
output and an input, are the same file, nor one output the folder another is written into.
After the run, `staged()` hands the writers temporary paths beside their targets and renames
them all into place only when every writer succeeded; if a rename fails, the ones before it
are undone. So a failed run creates, replaces or deletes none of the user's files, and a
robot never picks up a half-written or mismatched trajectory. Any OS error becomes one
InputError line naming the file (exit 2).

Within a command (io/commits.py, cli.group.exit_code) the renames wait until the command has
returned and its lines have reached standard output: a command that then fails (standard
output full or closed) leaves no file either. Two commands writing into the same folders
rename, keep or undo their sets one after the other (FolderLocks), so each set lands whole.

The writers below write to the path they are given: inside `staged()`, a temporary. (A
script writing one file the same way: `with OutputSet({"out": path}).staged() as files:
write_csv(files["out"], ...)`.)
"""

from __future__ import annotations

import contextlib
import csv
import datetime as _dt
import errno
import hashlib
import io
import json
import math
import os
import re
import shutil
import stat
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..parallel.signals import signals_deferred
from .commits import DEFERRED

HDF5_SCHEMA_VERSION = 2  # 2: `units` on every dataset, provenance and library versions on the file

NAME_MAX = 255  # bytes in one file name on the usual file systems (ext4, xfs, btrfs, tmpfs, NTFS)

PathLike = str | Path


class OutputSet:
    """The outputs of one command, `{label: path}` (None entries are ignored), and the input
    files they must not overwrite. Labels name the option in messages (`--export`)."""

    def __init__(self, outputs: Mapping[str, PathLike | None],
                 inputs: Mapping[str, PathLike | None] | None = None):
        self.outputs = {label: Path(path) for label, path in outputs.items() if path is not None}
        self.inputs = {label: Path(path) for label, path in (inputs or {}).items() if path is not None}

    def check(self) -> OutputSet:
        """Raise one InputError listing every output that cannot be written or coincides with
        another output or an input; nothing is created."""
        lines, blocked = [], set()  # folders already reported: one line for all their files
        labels = []  # the outputs whose target could be looked up, for the coincidences
        for label, path in self.outputs.items():
            try:
                line = _file_problem(label, path)
                folder = _target(path).parent
                if line is None and folder not in blocked:
                    line = _folder_problem(label, path)
                    if line is not None:
                        blocked.add(folder)
                labels.append(label)
            except OSError as error:  # the path itself cannot be looked up
                line = _path_problem(label, path, error)
            if line is not None:
                lines.append(line)
        for i, label in enumerate(labels):
            path = self.outputs[label]
            for other in labels[:i]:
                if same_file(path, self.outputs[other]):
                    lines.append(f"{label}: got {path}, expected a file other than {other} "
                                 f"({self.outputs[other]})")
                    break
            new_file = None if path.exists() else _target(path)
            for other in labels:  # a new file where another output's new folder is to be made
                if other != label and new_file is not None and new_file in _target(self.outputs[other]).parents:
                    lines.append(f"{label}: got {path}, the folder of {other} ({self.outputs[other]}); "
                                 "expected a file name")
                    break
            for other, source in self.inputs.items():
                if same_file(path, source):
                    lines.append(f"{label}: got {path}, expected a file other than the input "
                                 f"{other} ({source})")
        if lines:
            error = InputError("\n".join(lines))
            error.lines = lines
            raise error
        return self

    @contextlib.contextmanager
    def staged(self) -> Iterator[dict[str, Path]]:
        """`{label: temporary path}` for the writers; on success every temporary is renamed
        onto its target (within deferred_commits: when it commits), on any failure all are
        removed and folders made for them too."""
        self.check()
        staged = _Staged({label: _target(path) for label, path in self.outputs.items()}, self.outputs)
        try:
            with signals_deferred():  # an interrupt between making a file and noting it left it behind
                for label, target in staged.targets.items():
                    staged.made += _make_folders(target.parent, self.outputs[label], label)
                    staged.temporaries[label] = _temporary(target, self.outputs[label], label)
            try:
                yield dict(staged.temporaries)
            except OSError as error:
                raise _os_error(error, staged.temporaries, self.outputs) from None
        except BaseException:
            staged.discard()
            raise
        deferred = DEFERRED.get()
        if deferred is None:
            staged.commit()
        else:
            deferred.add(staged, commit_staged, lock_staged)


def lock_staged(pending: list[_Staged]) -> FolderLocks:
    """The folders every staged set renames into, locked (FolderLocks.waiting)."""
    return FolderLocks.waiting([target.parent for staged in pending for target in staged.targets.values()])


def commit_staged(pending: list[_Staged], locks: FolderLocks | None = None) -> Renamed:
    """Rename the temporaries of every staged set onto their targets, all or none; the
    replaced files' backups are kept until the Renamed is kept or undone, and `locks`
    (lock_staged's) held until then."""
    temporaries, targets, paths = {}, {}, {}
    for staged in pending:
        for label, temporary in staged.temporaries.items():
            key = label if label not in temporaries else f"{label} ({len(temporaries)})"
            temporaries[key], targets[key], paths[key] = temporary, staged.targets[label], staged.paths[label]
    renamed = _rename_all(temporaries, targets, paths, locks)
    for staged in pending:
        staged.temporaries = {}
    return renamed


LOCK_POLL_SECONDS = 0.02  # between tries for a folder another command is renaming into


class FolderLocks:
    """Exclusive flock(2) locks on folders outputs are renamed into, taken in path order and
    held from the renames until they are kept or undone. Two commands writing the same
    outputs used to interleave: one's renames between the other's left a mixed set, and one
    undoing its renames (its standard output closed) put back files over the other's, which
    had reported them written. A folder that cannot be opened (or a system without flock)
    goes unlocked."""

    def __init__(self, handles: list[int]):
        self.handles = handles

    @classmethod
    def waiting(cls, folders: Sequence[Path]) -> FolderLocks:
        """Lock `folders`, waiting while another process holds one; the wait polls, so an
        interrupt ends it (nothing renamed yet)."""
        try:
            import fcntl
        except ImportError:  # not a POSIX system
            return cls([])
        locks = cls([])
        try:
            for folder in sorted({str(folder) for folder in folders}):
                try:
                    handle = os.open(folder, os.O_RDONLY)
                except OSError:
                    continue
                locks.handles.append(handle)
                while True:
                    try:
                        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        break
                    except BlockingIOError:
                        time.sleep(LOCK_POLL_SECONDS)
                    except OSError:  # a file system without locks
                        break
        except BaseException:
            locks.release()
            raise
        return locks

    def release(self) -> None:
        for handle in self.handles:
            with contextlib.suppress(OSError):
                os.close(handle)  # closing the last descriptor releases the lock
        self.handles = []


class _Staged:
    """An OutputSet's temporaries, written, waiting to be renamed onto their targets."""

    def __init__(self, targets: dict[str, Path], paths: dict[str, Path]):
        self.targets, self.paths = targets, paths
        self.temporaries: dict[str, Path] = {}
        self.made: list[Path] = []  # folders made for the targets, removed if nothing lands

    def commit(self) -> None:
        try:
            locks = lock_staged([self])
            with signals_deferred():  # an interrupt between two renames: some files replaced, backups left
                _rename_all(self.temporaries, self.targets, self.paths, locks).keep()
        except BaseException:
            self.discard()
            raise
        self.temporaries = {}

    def discard(self) -> None:
        for temporary in self.temporaries.values():
            with contextlib.suppress(OSError):
                os.unlink(temporary)
        self.temporaries = {}
        for folder in reversed(self.made):
            with contextlib.suppress(OSError):
                folder.rmdir()


def check_outputs(outputs: Mapping[str, PathLike | None],
                  inputs: Mapping[str, PathLike | None] | None = None) -> OutputSet:
    """Before any work: the command's outputs can all be written and overwrite no input."""
    return OutputSet(outputs, inputs).check()


# --- the checks ----------------------------------------------------------------------------


def _target(path: Path) -> Path:
    """Where the file lands: a symbolic link's file, so the link itself stays."""
    try:
        return path.resolve()
    except RuntimeError:  # a loop of symbolic links (an OSError itself from Python 3.13 on)
        raise OSError(errno.ELOOP, os.strerror(errno.ELOOP), str(path)) from None


def same_file(a: Path, b: Path) -> bool:
    try:
        return _target(a) == _target(b) or os.path.samefile(a, b)  # samefile: hard links, bind mounts
    except OSError:  # one of them does not exist yet, or cannot be looked up
        return False


def _path_problem(label: str, path: Path, error: OSError) -> str:
    """Why `path` cannot even be looked up: a name too long, a loop of symbolic links."""
    reason = error.strerror or str(error)
    if error.errno == errno.ELOOP:
        return f"{label}: got {path}, a loop of symbolic links; expected a file name ({reason})"
    if error.errno == errno.ENAMETOOLONG:
        longest = max(len(os.fsencode(part)) for part in path.parts)
        if longest > NAME_MAX:  # else the whole path is too long
            return f"{label}: got {path}, a name of {longest} bytes; expected at most {NAME_MAX} ({reason})"
    return f"{label}: cannot write {path}: {reason}"


# names of a process's own streams: whatever they stand for (a redirected file, a pipe), an
# output is written whole beside its target and renamed onto it, which a stream cannot take
# (POSIX keeps a leading `//`, so the slashes may be doubled)
_STREAM_NAMES = re.compile(r"/+dev/+(stdin|stdout|stderr)$|/+dev/+fd/|/+proc/+[^/]+/+fd/")


def _is_stream(path: Path, target: Path) -> bool:
    """`path` names one of this process's standard streams, by name or (a symbolic link to
    one, standard output redirected to that very file) by being the file one is written to."""
    if any(_STREAM_NAMES.match(str(name)) for name in (Path(os.path.abspath(path)), target)):
        return True
    try:
        written = os.stat(target)
    except OSError:  # not there yet: no stream writes to it
        return False
    for descriptor in (1, 2):
        try:
            stream = os.fstat(descriptor)
        except OSError:  # closed
            continue
        if (stream.st_dev, stream.st_ino) == (written.st_dev, written.st_ino):
            return True
    return False


def _file_problem(label: str, path: Path) -> str | None:
    """What about the target itself stops `path` from being written, or None."""
    target = _target(path)
    if _is_stream(path, target):
        return f"{label}: got {path}, a process's stream; expected a file name"
    if target.is_dir():
        return f"{label}: got {path}, a folder; expected a file name"
    if target.exists() or target.is_symlink():
        if not target.is_file():
            return f"{label}: got {path}, not a regular file; expected a file name"
        # no write permission for anyone: read-only, though root's access test passes
        if not os.access(target, os.W_OK) or not target.stat().st_mode & 0o222:
            return f"{label}: cannot write {path}: the file is read-only"
    return None


def _folder_problem(label: str, path: Path) -> str | None:
    """What about its folder stops `path` from being written, or None."""
    target = _target(path)
    folder = next(parent for parent in target.parents if parent.exists() or parent == parent.parent)
    if not folder.is_dir():
        return f"{label}: cannot write {path}: {folder} is not a folder"
    try:  # the real test: a new file in the folder that exists (as root, permissions pass)
        handle, probe = tempfile.mkstemp(prefix=".stitchplan-probe.", dir=folder)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        return f"{label}: cannot write {path}: cannot create a file in {folder} ({error.strerror or error})"
    return None


# --- staging and renaming ------------------------------------------------------------------


def _make_folders(folder: Path, path: Path, label: str) -> list[Path]:
    """Create `folder` and its missing parents; returns those created, outermost first."""
    missing = [p for p in [folder, *folder.parents] if not p.exists()][::-1]
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise InputError(f"{label}: cannot write {path}: {error.strerror or error} ({folder})") from None
    return missing


def _sibling_prefix(target: Path) -> str:
    """`.name.` for a temporary or backup beside `target`, the name cut so that a target whose
    name is near the limit still gets one (the random part and suffix take 12 bytes)."""
    return "." + os.fsdecode(os.fsencode(target.name)[:NAME_MAX - 16]) + "."


def _temporary(target: Path, path: Path, label: str) -> Path:
    try:
        handle, name = tempfile.mkstemp(prefix=_sibling_prefix(target), suffix=".tmp", dir=target.parent)
    except OSError as error:
        raise InputError(f"{label}: cannot write {path}: {error.strerror or error}") from None
    os.close(handle)
    return Path(name)


def _file_mode(target: Path) -> int:
    """An existing target's permissions, else the usual mode of a new file (mkstemp gives 0600)."""
    try:
        return stat.S_IMODE(target.stat().st_mode)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


class Renamed:
    """Temporaries renamed onto their targets, with backups of what they replaced: `keep()`
    drops the backups, `undo()` puts them back and removes what the renames created."""

    def __init__(self, targets: dict[str, Path], locks: FolderLocks | None = None):
        self.targets = targets
        self.backups: dict[str, Path] = {}
        self.labels: list[str] = []  # renamed, in order
        self.locks = locks  # on the targets' folders, released once kept or undone

    def keep(self) -> None:
        for backup in self.backups.values():
            with contextlib.suppress(OSError):
                os.unlink(backup)
        self.backups, self.labels = {}, []
        if self.locks is not None:
            self.locks.release()

    def undo(self) -> None:
        for done in reversed(self.labels):
            with contextlib.suppress(OSError):
                if done in self.backups:
                    os.replace(self.backups.pop(done), self.targets[done])
                else:
                    os.unlink(self.targets[done])
        self.keep()


def _rename_all(temporaries: dict[str, Path], targets: dict[str, Path], paths: dict[str, Path],
                locks: FolderLocks | None = None) -> Renamed:
    """Rename each temporary onto its target, keeping a backup (hard-linked or copied) of
    each file replaced; if one fails, undo the earlier ones (and release `locks`)."""
    renamed = Renamed(targets, locks)
    label = ""
    try:
        for label, temporary in temporaries.items():
            target = targets[label]
            os.chmod(temporary, _file_mode(target))
            if target.exists():
                renamed.backups[label] = _backup(target)
            os.replace(temporary, target)
            renamed.labels.append(label)
    except OSError as error:
        renamed.undo()
        raise InputError(f"{label}: cannot write {paths[label]}: {error.strerror or error}") from None
    return renamed


def _backup(target: Path) -> Path:
    """A second name for the target's current content, in its folder."""
    handle, name = tempfile.mkstemp(prefix=_sibling_prefix(target), suffix=".old", dir=target.parent)
    os.close(handle)
    try:
        os.unlink(name)
        os.link(target, name)  # the same inode: restoring it restores the file exactly
    except OSError:
        shutil.copy2(target, name)  # a file system without hard links
    return Path(name)


def _os_error(error: OSError, temporaries: dict[str, Path], paths: dict[str, Path]) -> InputError:
    """A writer's OS error as one line naming the output it was writing."""
    where = str(getattr(error, "filename", "") or "")
    for label, temporary in temporaries.items():
        if where == str(temporary) or where.endswith(temporary.name):
            return InputError(f"{label}: cannot write {paths[label]}: {error.strerror or error}")
    names = ", ".join(str(path) for path in paths.values())
    return InputError(f"cannot write the outputs ({names}): {error.strerror or error}")


# --- provenance ----------------------------------------------------------------------------


POINT_DECIMALS = 12  # points and displacements (mm) to 1e-12 mm: 0, not the round-off 5.4e-16 of an exit on x = 0


def rounded_point(point) -> np.ndarray | None:
    """A point (or displacements) in mm as the outputs write it, rounded to POINT_DECIMALS,
    -0 made 0 (the errors reported are the unrounded points')."""
    return None if point is None else np.round(np.asarray(point, dtype=float), POINT_DECIMALS) + 0.0


def sha256(path: PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def provenance(command: Sequence[str] | None = None, scenario: PathLike | None = None,
               scenario_sha256: str | None = None) -> dict:
    """Who wrote a result and from what: version, the command line (argv as a list), the
    scenario file and its SHA-256 (`scenario_sha256`: of the bytes the run parsed, which a
    pipe cannot give twice; else of the file as it is now), the time, and the folder the
    command ran in (`working_directory`: what relative paths in the command line and the
    record are relative to)."""
    from .. import __version__, source_sha256

    return {
        "stitchplan_version": __version__,
        "stitchplan_source_sha256": source_sha256(),
        "command": list(command) if command is not None else None,
        "scenario": str(scenario) if scenario is not None else None,
        "scenario_sha256": scenario_sha256 or _sha256_or_none(scenario),
        "created_utc": utc_now(),
        "working_directory": working_directory(),
    }


def working_directory() -> str | None:
    """The folder the command runs in (None when it no longer exists)."""
    try:
        return os.getcwd()
    except OSError:
        return None


def _sha256_or_none(path: PathLike | None) -> str | None:
    if path is None:
        return None
    try:
        return sha256(path)
    except OSError as error:
        raise InputError(f"{path}: cannot be read ({error.strerror or error})") from None


# --- writers -------------------------------------------------------------------------------


@contextlib.contextmanager
def _naming(path: PathLike) -> Iterator[None]:
    """A failed write or close (a full disk, a file-size limit) names no file by itself: name
    `path`, so that the output set can say which output it was."""
    try:
        yield
    except OSError as error:
        if error.filename is None:
            error.filename = os.fspath(path)
        raise


def write_text(path: PathLike, text: str) -> None:
    with _naming(path), open(path, "w") as handle:
        handle.write(text)


def write_bytes(path: PathLike, data: bytes | memoryview) -> None:
    with _naming(path), open(path, "wb") as handle:
        handle.write(data)


def write_csv(path: PathLike, columns: Sequence[str], rows: np.ndarray | Sequence[Sequence[Any]],
              precision: int | None = 9) -> None:
    """Rows under a header; floats with `precision` significant digits, or (None) as the
    shortest text that reads back as the same double."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_format(value, precision) for value in row])
    write_text(path, buffer.getvalue())


def _format(value: Any, precision: int | None) -> Any:
    if isinstance(value, (float, np.floating)):
        if precision is None:
            text = repr(float(value))
            return text[:-2] if text.endswith(".0") else text
        return f"{float(value) + 0.0:.{precision}g}"  # + 0.0: a rounded -0.0 is written as 0
    if isinstance(value, np.integer):
        return int(value)
    return value


def _plain(value: Any, finite: bool = False) -> Any:
    """Python's own types for numpy's, through dicts and lists; with `finite`, a float that
    is not finite becomes None."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, (np.floating, np.integer)):
        value = value.item()
    if isinstance(value, dict):
        return {k: _plain(v, finite) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, finite) for v in value]
    if finite and isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: PathLike, data: dict) -> None:
    """JSON as the standard has it: a number that is not finite (not available, or failed)
    is written null, not as the NaN or Infinity that strict parsers refuse."""
    write_text(path, json.dumps(_plain(data, finite=True), indent=2, allow_nan=False) + "\n")


def write_yaml(path: PathLike, data: dict, header: str = "") -> None:
    import yaml

    write_text(path, header + yaml.safe_dump(_plain(data), sort_keys=False))


def write_hdf5(path: PathLike, groups: dict[str, dict[str, Any]], attributes: dict[str, Any],
               units: Mapping[str, str]) -> None:
    """groups: {"group/sub": {"dataset": array, ...}}; attributes go on the root with the
    schema version and the library versions. Every dataset gets a `units` attribute, looked
    up in `units` as "group/dataset", then "dataset"; a dataset without one is a bug.

    The file is built in memory, then written like every other output: a write that fails
    inside the HDF5 library is not an ordinary error (on a full disk the process crashed
    while closing the file), a failed ordinary write raises an OSError that names `path`."""
    import platform

    import h5py
    import scipy

    image = io.BytesIO()
    with h5py.File(image, "w") as handle:
        for key, value in attributes.items():
            handle.attrs[key] = _attribute(value)
        handle.attrs["schema_version"] = HDF5_SCHEMA_VERSION
        handle.attrs["python_version"] = platform.python_version()
        handle.attrs["numpy_version"] = np.__version__
        handle.attrs["scipy_version"] = scipy.__version__
        handle.attrs["h5py_version"] = h5py.__version__
        for group_name, datasets in groups.items():
            group = handle.require_group(group_name)
            for name, value in datasets.items():
                if isinstance(value, str):
                    dataset = group.create_dataset(name, data=_text(value), dtype=h5py.string_dtype())
                else:
                    data = np.asarray(value)
                    options = {"compression": "gzip", "compression_opts": 4} if data.size > 1000 else {}
                    dataset = group.create_dataset(name, data=data, **options)
                dataset.attrs["units"] = _units(units, group_name, name)
    write_bytes(path, image.getbuffer())


def _units(units: Mapping[str, str], group: str, name: str) -> str:
    for key in (f"{group}/{name}", name):
        if key in units:
            return units[key]
    raise KeyError(f"HDF5 dataset {group}/{name} has no units: add it to the writer's units table")


def _attribute(value: Any) -> Any:
    if value is None:
        return "null"
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(_plain(value))
    if isinstance(value, str):
        return _text(value)
    return value


def _text(value: str) -> str:
    """`value` as UTF-8 can hold it: a path read under an ASCII-only locale carries its
    non-ASCII bytes as lone surrogates, which HDF5's UTF-8 strings refuse; they are kept as
    \\udcXX escapes, as the JSON summary writes them."""
    return value.encode("utf-8", "backslashreplace").decode("utf-8")
