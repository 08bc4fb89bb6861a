"""Traces and G-code to thermal boundary conditions (not built yet)."""
