"""The monitoring daemon (not built yet)."""
