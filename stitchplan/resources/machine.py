"""The machine's memory available to a run: what is free now, within the address-space limit."""

from __future__ import annotations

import os

# What a command maps after the guard beyond its runs' memory, counted against an address-space
# limit (`ulimit -v`): the libraries its run loads (cvxopt's and SciPy's OpenBLAS, LAPACK, SuperLU),
# their buffers and the allocator's reservations. VmPeak - VmSize at the guard: 310 MB for
# `deform configs/slab_edge_load.yaml` (a run estimated 13 MB above BASE_MEMORY), 158-231 MB for
# simulate and plan on the shipped needle scenes. The address space a run maps grows ~2.3x as fast
# as its memory (1824 MB for deform at spacing 1 mm, estimated 798 MB), which the memory share's
# half covers. Past the limit an allocation fails: SuperLU then spun without end (SIGTERM unheard),
# CHOLMOD crashed.
ADDRESS_SPACE_RESERVE = 320e6


def available_memory() -> float | None:
    """Bytes of memory available now (MemAvailable of /proc/meminfo, else the physical
    memory), and no more than the process's address-space limit leaves (`ulimit -v`) after
    ADDRESS_SPACE_RESERVE; None when unknown."""
    memory = system_memory()
    room = address_space_left()
    if room is None:
        return memory
    return room if memory is None else min(memory, room)


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


def address_space_left() -> float | None:
    """Bytes the address-space limit (RLIMIT_AS) leaves above what the process maps now
    (VmSize) and ADDRESS_SPACE_RESERVE, None without a limit."""
    try:
        import resource

        limit, _ = resource.getrlimit(resource.RLIMIT_AS)
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as handle:
            mapped = next((float(line.split()[1]) * 1024.0 for line in handle if line.startswith("VmSize:")), 0.0)
    except (ImportError, OSError, ValueError):
        return None
    return max(float(limit) - mapped - ADDRESS_SPACE_RESERVE, 0.0)
