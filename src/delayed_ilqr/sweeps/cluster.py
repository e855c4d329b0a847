"""Batches on ``dask.distributed``: a ``LocalCluster`` of worker processes, or any scheduler.

Each worker is set up once by a plugin (float64, XLA's CPU flags, the persistent compilation
cache: `compute.prepare_process`), compiles each solver once and keeps it for every batch
of the same structure, and returns only the batch's statistics; the process that runs the sweep
writes them to the store as they arrive, so that a batch computed twice (its worker died after
finishing it, and the scheduler ran it again) is written once. A worker that dies mid-batch loses
that batch only: the scheduler runs it again on another worker (up to
``distributed.scheduler.allowed-failures`` times).
"""
from __future__ import annotations

import contextlib
from typing import Iterator, Optional

from distributed import Client, LocalCluster
from distributed.diagnostics.plugin import WorkerPlugin

from .compute import prepare_process

__all__ = ["client_for", "SweepWorkerSetup"]


class SweepWorkerSetup(WorkerPlugin):
    """A Dask worker plugin (``client.register_plugin``): `compute.prepare_process` on
    each worker, once, before it computes anything."""

    name = "delayed-ilqr-sweep-setup"

    def __init__(self, cache: bool = True, cache_dir: Optional[str] = None):
        self.cache, self.cache_dir = cache, cache_dir

    def setup(self, worker=None):
        prepare_process(self.cache_dir, self.cache)



@contextlib.contextmanager
def client_for(scheduler, n_workers: int, cache: bool, cache_dir) -> Iterator:
    """A ``distributed.Client`` for ``scheduler``: "local" starts a ``LocalCluster`` of ``n_workers``
    single-threaded worker processes (closed on exit); an address such as ``tcp://host:8786``
    connects to a running scheduler; a ``Client`` is used as it is. Registers the worker set-up."""
    if isinstance(scheduler, Client):
        client, owned = scheduler, None
    elif scheduler == "local":
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None)
        client, owned = Client(cluster), cluster
    elif isinstance(scheduler, str):
        client, owned = Client(scheduler), None
    else:
        raise TypeError(f"scheduler must be None, 'local', a scheduler address or a distributed.Client; "
                        f"got {type(scheduler).__name__}")
    try:
        client.register_plugin(SweepWorkerSetup(cache, None if cache_dir is None else str(cache_dir)),
                               name=SweepWorkerSetup.name)
        yield client
    finally:
        if owned is not None:
            client.close()
            owned.close()
