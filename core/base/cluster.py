"""Connection to a Dask distributed cluster, the optional engine of the command line
for large collections: `tcp://host:8786` (a running scheduler) or `local:N` (a LocalCluster of N
single-threaded worker processes on this machine, closed again afterwards).

Dask is an optional extra (`pip install ".[dask]"` in the checkout, or
`pip install "dask[distributed]"` beside an installed core), never a requirement of the
core or the Blender extension: it is imported here, and only when a scheduler is asked
for. The workers must have the same version of this package installed (they unpickle
its tasks).
"""

from __future__ import annotations

from contextlib import contextmanager

from .errors import ShapeGenError

__all__ = ["ClusterError", "INSTALL_HINT", "connect", "parse_scheduler"]

INSTALL_HINT = 'pip install "dask[distributed]"'


class ClusterError(ShapeGenError, ValueError):
    """A scheduler address that cannot be used, or Dask missing."""


def parse_scheduler(scheduler: str) -> tuple[str, int | str]:
    """("local", N) for `local:N`, else ("address", the address). A scheme other than
    tcp/tls/inproc/ws/wss/ucx is refused with the accepted forms."""
    text = str(scheduler).strip()
    if text.startswith("local:"):
        count = text[len("local:"):]
        if not count.isdigit() or int(count) < 1:
            raise ClusterError(f"--scheduler {text}: local:N needs a number of workers N >= 1")
        return "local", int(count)
    if "://" in text and text.split("://", 1)[0] in ("tcp", "tls", "inproc", "ws", "wss", "ucx") and \
            text.split("://", 1)[1]:
        return "address", text
    raise ClusterError(f"--scheduler {text}: expected a scheduler address such as tcp://host:8786, or local:N")


@contextmanager
def connect(scheduler: str):
    """A dask.distributed Client for `scheduler` (see module docstring), closed (with its
    LocalCluster, if it started one) when the block ends."""
    kind, value = parse_scheduler(scheduler)
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ClusterError(f"--scheduler {scheduler} needs Dask distributed, which is not installed: "
                           f"{INSTALL_HINT}") from None
    cluster = None
    try:
        if kind == "local":
            cluster = LocalCluster(n_workers=value, threads_per_worker=1, processes=True, dashboard_address=None,
                                   env={"OPENBLAS_NUM_THREADS": "1"})
            client = Client(cluster)
        else:
            client = Client(value, timeout="20s")
    except OSError as exc:
        if cluster is not None:
            cluster.close()
        raise ClusterError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
