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


@pytest.fixture(autouse=True)
def _root_logging_restored():
    """A command run in process (main([...])) installs its stderr handler on the root logger;
    the handler would outlive the test's captured stderr and print "Logging error ... closed
    file" in a later one. Each test gets the root logger back as it found it."""
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    canopen_level = logging.getLogger("canopen").level
    yield
    for h in list(root.handlers):  # pytest's own capture handlers come and go by themselves
        if h not in handlers and type(h).__module__.startswith("logging"):
            root.removeHandler(h)
            h.close()
    root.setLevel(level)
    logging.getLogger("canopen").setLevel(canopen_level)
