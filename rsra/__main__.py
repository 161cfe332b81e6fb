"""``python -m rsra`` runs the ``rsra`` command."""
from rsra.daq.cli import main

raise SystemExit(main())
