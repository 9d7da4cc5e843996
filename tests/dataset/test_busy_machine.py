"""A busy machine (loaded, or running other dask clusters: a second build, another test run) must
fail no test and disturb no build: nothing here may depend on how fast or how idle it is."""

from __future__ import annotations

import pytest


def _add(a: int, b: int) -> int:
    return a + b


def test_two_local_clusters_at_once_start_without_a_warning():
    """`local_cluster` serves the scheduler's HTTP routes on a free port: a second cluster on the
    machine (another build, another test run) is no reason for a warning, and the suite's
    ``filterwarnings = error`` would make that warning a failed start."""
    pytest.importorskip("distributed")
    from distributed import Client

    from jaxfish.dataset import local_cluster

    with local_cluster(1, processes=False) as first, local_cluster(1, processes=False) as second, \
            Client(first) as a, Client(second) as b:
        assert a.submit(_add, 1, 2, pure=False).result() == 3 and b.submit(_add, 3, 4, pure=False).result() == 7


def test_slow_scratch_directories_fail_no_dask_test(monkeypatch):
    """dask.distributed warns (``UserWarning``) when creating a server's scratch directory took
    over 1 s, as it can at load 6 on 2 cores; the suite's ``filterwarnings = error`` must not turn
    that into a failed cluster start (tests/conftest.py ignores that one warning)."""
    pytest.importorskip("distributed")
    import distributed.diskutils
    import distributed.utils
    from distributed import Client

    from jaxfish.dataset import local_cluster

    real_clock, real_workspace = distributed.utils.time, distributed.diskutils.WorkSpace.__init__
    lag = [0.0]

    def slow_workspace(self, *args, **kwargs):
        real_workspace(self, *args, **kwargs)
        lag[0] += 5.0  # creating it "took" 5 s on distributed's clock

    monkeypatch.setattr(distributed.utils, "time", lambda: real_clock() + lag[0])
    monkeypatch.setattr(distributed.diskutils.WorkSpace, "__init__", slow_workspace)
    with local_cluster(1, processes=False) as cluster, Client(cluster) as client:
        assert client.submit(_add, 1, 2, pure=False).result() == 3
    assert lag[0] >= 5.0  # the slow path was taken
