"""The plain-text table every benchmark script prints before its JSON line."""

from __future__ import annotations


def table(rows: list[dict], cols: list[str]) -> str:
    """Rows of dicts as a ``|``-separated table with the given columns, each as wide as its widest cell."""
    w = [max(len(c), *(len(f"{r[c]}") for r in rows)) for c in cols]
    out = [" | ".join(c.ljust(k) for c, k in zip(cols, w)), "-+-".join("-" * k for k in w)]
    out += [" | ".join(f"{r[c]}".ljust(k) for c, k in zip(cols, w)) for r in rows]
    return "\n".join(out)
