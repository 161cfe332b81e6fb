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

The folders also sit inside ``rsra/`` as symbolic links (``rsra/daq -> ../daq``, …), so a
plain checkout is the package as installed: run from the repository's top, ``rsra.estimator``
is ``estimator/`` — for Python, mypy, pyright and an IDE alike, with nothing installed. A wheel
holds the folders themselves (the links are not packaged; ``[tool.setuptools.package-dir]``
maps them).
"""
__version__ = "0.1.0"
