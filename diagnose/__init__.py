"""Diagnosis of model discrepancies against measured data (not built yet)."""
