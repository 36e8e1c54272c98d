"""Figures of the package, one module per capability (Agg backend, no display needed)."""
