"""The foundations every layer stands on: errors, typed settings and the reading of older
files' settings (compat), progress and cancel, versioned `.npz` files, child processes,
and the optional Dask connection. Imports nothing else of the core."""
