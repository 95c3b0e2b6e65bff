import pathlib

import numpy as np
import pytest

DATA = pathlib.Path(__file__).parent / "data"


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False, help="also run the slow studies")


def pytest_configure(config):
    if config.getoption("--runslow"):
        # `-m 'not slow'` comes from addopts; --runslow lifts it.
        config.option.markexpr = ""


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def data_dir():
    return DATA
