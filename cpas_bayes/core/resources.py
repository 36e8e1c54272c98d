"""How much memory a command may take, checked before it starts.

A step that keeps per-run results (a Monte Carlo, a load comparison) says
what it would hold, in bytes, before it draws anything; :func:`check_memory`
refuses it, naming the option and what to do, when that is more than
``MEMORY_FRACTION`` of the memory available now (``MemAvailable`` of
``/proc/meminfo``; else free pages by ``os.sysconf``; else
``FALLBACK_AVAILABLE``). Refusing up front replaces being killed by the
kernel after minutes of work with a partial output folder.
"""

from __future__ import annotations

import os

from cpas_bayes.core.errors import InputError

MEMORY_FRACTION = 0.5                 # of the available memory, for one command's results
FALLBACK_AVAILABLE = 4 * 1024**3      # bytes assumed available where the system does not say


def available_memory() -> int:
    """Bytes of memory available to start new work without swapping (Linux MemAvailable; else free pages)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return FALLBACK_AVAILABLE


def memory_budget() -> int:
    """Bytes one command's kept results may take: ``MEMORY_FRACTION`` of :func:`available_memory`."""
    return int(MEMORY_FRACTION * available_memory())


def format_bytes(n) -> str:
    """``1.5 GB``, ``320 MB``, ``12 kB`` (powers of 1000, as the kernel's free tools print them)."""
    n = float(n)
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:,.1f} {unit}"
    return f"{n:,.0f} bytes"


def check_memory(need, source, where, what, fix):
    """Refuse (InputError at ``source``, ``where``) work that would hold ``need`` bytes beyond the budget.

    ``what`` says what would take the memory (e.g. "10,000,000 runs of 2 canopies × 2 stages"),
    ``fix`` what to do: a sentence, or a function of the budget in bytes returning one. Returns the budget.
    """
    available = available_memory()
    budget = int(MEMORY_FRACTION * available)
    if need > budget:
        raise InputError(source, where,
                         f"{what} would hold about {format_bytes(need)} in memory; the limit is "
                         f"{format_bytes(budget)} ({MEMORY_FRACTION:.0%} of the {format_bytes(available)} "
                         "available now)", fix if isinstance(fix, str) else fix(budget))
    return budget
