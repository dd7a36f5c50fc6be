"""The machine's memory available to a run: what is free now, within the address-space limit."""

from __future__ import annotations

import os

# An address-space limit (`ulimit -v`, RLIMIT_AS) counts what a process maps, not what it
# touches: a run needs max(VmSize now, NUMERICS_MAPPED) + ADDRESS_SPACE_RESERVE + ADDRESS_GROWTH
# x (its memory estimate - BASE_MEMORY) under it (address_space_needed). Measured as the least
# `ulimit -v` each command ran under (--no-resource-check; OPENBLAS_NUM_THREADS=1): deform
# slab_edge_load 448 MB (its run estimated 13 MB above BASE_MEMORY), at spacing 2 614 MB (122 MB);
# simulate sh12_100x100 409 MB (28 MB), at spacing 3.55 448 MB (117 MB); plan --no-verify 427 MB
# (37 MB): this model asks 1.04-1.6x of those. Short of it a run failed badly: SuperLU spun at a
# failed allocation (SIGTERM unheard), CHOLMOD crashed.
NUMERICS_MAPPED = 255e6  # VmSize once a command has imported the numerics (simulate at its guard)
# the most any command's imports map (~230-340 MB; calibrate material's optimizer included): a
# process that mapped more when a library failed to load had a run's arrays and factors mapped
IMPORTS_MAPPED_AT_MOST = 400e6
ADDRESS_SPACE_RESERVE = 180e6  # what a run maps beyond that besides its arrays: libraries loaded late, buffers
ADDRESS_GROWTH = 2.3  # address space mapped per byte of a run's memory (deform at spacing 1 mm: 1824 MB for 798)


def available_memory() -> float | None:
    """Bytes of memory available now (MemAvailable of /proc/meminfo, else the physical
    memory); None when unknown. An address-space limit is checked apart (address_space)."""
    return system_memory()


def system_memory() -> float | None:
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def address_space() -> tuple[float, float] | None:
    """(the address-space limit, RLIMIT_AS, and what the process maps now, VmSize), in bytes;
    None without a limit."""
    try:
        import resource

        limit, _ = resource.getrlimit(resource.RLIMIT_AS)
        if limit == resource.RLIM_INFINITY:
            return None
    except ImportError:
        return None
    return float(limit), status_bytes("VmSize") or 0.0


def mapped_peak() -> float | None:
    """The most address space this process has mapped (VmPeak), bytes; None where unknown."""
    return status_bytes("VmPeak")


def status_bytes(field: str) -> float | None:
    """A size line of /proc/self/status (`VmSize`, `VmPeak`: kB there) in bytes; None where unknown."""
    try:
        with open("/proc/self/status") as handle:
            return next((float(line.split()[1]) * 1024.0 for line in handle if line.startswith(f"{field}:")), None)
    except (OSError, ValueError, IndexError):
        return None


def address_space_needed(mapped: float, run_memory: float, base_memory: float) -> float:
    """Bytes of address space a run estimated at `run_memory` (BASE_MEMORY `base_memory`
    included) needs in a process mapping `mapped` bytes now (the constants above)."""
    return max(mapped, NUMERICS_MAPPED) + ADDRESS_SPACE_RESERVE + ADDRESS_GROWTH * max(run_memory - base_memory, 0.0)


def memory_within_address_space(limit: float, mapped: float, base_memory: float) -> float:
    """The largest run memory estimate (BASE_MEMORY `base_memory` included) whose address space
    fits under `limit` in a process mapping `mapped` bytes now (address_space_needed, inverted)."""
    return base_memory + (limit - address_space_needed(mapped, base_memory, base_memory)) / ADDRESS_GROWTH
