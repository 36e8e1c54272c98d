"""Imported by the workers' fork server alone: numba's compiler and runtime started there once, so that every
worker forked from it begins with them loaded.

A fresh process' first call of a compiled (cached) kernel took 0.26-0.69 s, most of it numba starting, and
every worker paid it on its first task; a process forked after one call here pays 0.02-0.05 s a kernel. No
kernel that starts threads runs here (a process forked after numba's thread pool has started aborts).
"""

from __future__ import annotations

import numba


@numba.njit(cache=True)
def _add_one(x):
    return x + 1.0


_add_one(1.0)
