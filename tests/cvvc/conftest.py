"""Fixtures of the cvvc tests: one local Dask cluster shared by the evaluations that do not test the cluster."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture(scope="session")
def dask_scheduler() -> Iterator[str]:
    """A LocalCluster of two worker processes on loopback, as ``cvvc evaluate`` starts one; yields its address.

    Started once per session (about 4 s) and handed to evaluations as ``scheduler=``; the tests of the cluster
    itself (the user cluster of tests/cvvc/test_campaign.py, the small evaluation of test_evaluate.py) start
    their own.
    """
    from distributed import LocalCluster

    # its HTTP server on a free loopback port, as cvvc.cluster's: None means port 8787, taken by any other suite
    # running on the machine (and Dask's warning is an error here)
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address="127.0.0.1:0", protocol="tcp")
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()
