"""The common base of every error hybridcomp raises on bad input or state.

Each error also subclasses the built-in exception it is (``ValueError`` for bad files and values,
``RuntimeError`` for failed runs), so ``except ValueError`` keeps working; ``except HybridcompError``
catches all of them and nothing else.
"""


class HybridcompError(Exception):
    """Base of hybridcomp's errors; the message names the file, the field and the value."""
