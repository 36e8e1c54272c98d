"""Foundation used by every layer: errors, unit systems, atomic file writing and JSON, the executor
(this process, local processes or Dask). Imports nothing else of the package.
"""
