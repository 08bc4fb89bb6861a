"""Characteristic diagrams: regression, XML, database (not built yet)."""
