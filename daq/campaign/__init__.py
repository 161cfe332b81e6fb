"""Campaigns: many recordings reprocessed into one dataset (docs/user-guide.md "Campaigns")."""
