"""The caches of compiled functions and rig tables on a Dask cluster's workers (the optional `dask` extra)."""

from __future__ import annotations

from distributed import WorkerPlugin


class CachesOnWorkers(WorkerPlugin):
    """Gives each worker, when it joins the cluster or starts, the submitting process's cache settings: JAX's
    persistent compilation cache (`jax_settings`, `jax.config` names to values) and the rig tables' folder
    (`table_folder`, see `table_cache.py`; None: none). Workers on other machines need those folders on a file
    system they share (as the batch's images); where a folder cannot be written, a worker goes on without it
    (JAX warns about the compiled functions it could not keep)."""

    name = "jaxstereo-caches"

    def __init__(self, jax_settings: dict, table_folder):
        self.jax_settings = jax_settings
        self.table_folder = table_folder

    def setup(self, worker) -> None:
        from .batch import _use_caches

        _use_caches(self.jax_settings, self.table_folder)
