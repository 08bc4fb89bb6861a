"""hybridcomp: hybrid thermal error compensation for machine tools."""

__version__ = "0.1.0"
