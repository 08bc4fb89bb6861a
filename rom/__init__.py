"""Krylov reduced-order structure model (not built yet)."""
