"""Thermo-elastic finite element model of a machine tool."""
