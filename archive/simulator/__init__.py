"""Simulated Resonon flights with known ground truth (``archive simulate``).

``simulate_flight`` (in :mod:`archive.simulator.command`) writes a flight and returns its
:class:`~archive.simulator.truth.Truth`; ``load_truth`` reads it back. Both are importable from
here, lazily, so that importing the package stays cheap.
"""

from __future__ import annotations

__all__ = ["load_truth", "simulate_flight"]


def __getattr__(name: str):
    if name == "simulate_flight":
        from archive.simulator.command import simulate_flight
        return simulate_flight
    if name == "load_truth":
        from archive.simulator.truth import load_truth
        return load_truth
    raise AttributeError(f"module 'archive.simulator' has no attribute {name!r}")
