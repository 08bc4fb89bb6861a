"""The version of hybridcomp (one place: ``hybridcomp.__version__`` and every file that records it)."""

__version__ = "0.1.0"
