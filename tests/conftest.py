import numpy as np
import pytest

from rsra.config.rig import load_config


@pytest.fixture(scope="session")
def cfg():
    return load_config()


@pytest.fixture(scope="session")
def model(cfg):
    return cfg.rig_model()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
