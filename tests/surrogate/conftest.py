"""Fixtures of the surrogate tests: one torch thread, tiny synthetic datasets."""

import numpy as np
import pytest
import torch

from calendaring.data.dataset import synthetic_dataset, write_dataset


@pytest.fixture(scope="session", autouse=True)
def _one_thread():
    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_ds():
    """40 design runs + 2 replicate groups of 3 runs, the last 4 design runs as holdout."""
    ds = synthetic_dataset(40, seed=1, replicate_groups=2, replicates=3, noise=0.02)
    role = ds.role.copy()
    role[36:40] = "holdout"
    ds.role = role
    return ds


@pytest.fixture(scope="session")
def tiny_h5(tiny_ds, tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "tiny.h5", tiny_ds)


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(0)
