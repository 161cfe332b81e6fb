"""`rsra campaign`: many recordings reprocessed into one dataset (docs/cli.md)."""
