"""rsra — rotor hub loads from load cells (after the NASA RSRA load-cell report).

One import namespace for the installed distribution; the source folders stay at the top of the
repository and are installed under it (see ``[tool.setuptools.package-dir]`` in pyproject.toml):

* ``rsra.config``    — ``config/``: the neutral rig description (``rsra.config.rig``: typed
  configuration, sections, units, configuration errors) beside the default rig TOML, EDS files,
  scenarios and Zenoh configs it describes. Imports nothing of ours but ``rsra.estimator.params``.
* ``rsra.estimator`` — ``estimator/``: pure numerics (balance, filters, identification).
* ``rsra.sim_bus``   — ``sim_bus/``: the stand-in aircraft (simulated CANopen nodes and physics).
* ``rsra.daq``       — ``daq/``: the shell (CAN/CANopen I/O, runtime, analysis, command line).

``python -m rsra`` is the ``rsra`` command.

The editable install (``make setup``) is a tree of links to these folders on a ``.pth`` path
(setuptools' strict mode, which static tools read). Run from the repository's top, this folder
``rsra/`` comes first on ``sys.path`` and holds no ``daq/``: ``extend_path`` adds every other
``rsra/`` on ``sys.path`` (the link tree's) to this package's path, so ``rsra.daq`` is found
there. In a plain install there is one ``rsra/`` and it changes nothing.
"""
from pkgutil import extend_path

__path__ = extend_path(__path__, __name__)
__version__ = "0.1.0"
