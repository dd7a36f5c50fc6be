"""stitchplan: curved suture needle insertion simulation and trajectory planning."""

import functools

# the one place the version is written: pyproject.toml reads it ([tool.setuptools.dynamic]),
# run logs record it, `stitchplan --version` prints it
__version__ = "0.2.0"


@functools.cache  # read once a process (every record, PNG and worker check asks): the code it imported
def source_sha256() -> str:
    """SHA-256 of the package's Python sources, their paths and bytes in path order: the code
    a result came from, which the version alone does not say (it stays the same over many
    changes of the numerics between releases). Records carry it beside the version."""
    from pathlib import Path

    return sources_digest(Path(__file__).resolve().parent)


def sources_digest(root) -> str:
    import hashlib

    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py"), key=lambda p: p.relative_to(root).as_posix()):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()
