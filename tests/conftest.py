"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

RESONON_SAMPLES = Path(__file__).resolve().parents[1].parent / "shared" / "samples" / "resonon"


@pytest.fixture
def resonon_samples() -> Path:
    """Folder of real Resonon/Spectronon files (read only, never copied); skips when absent."""
    if not RESONON_SAMPLES.is_dir():
        pytest.skip(f"real Resonon samples not found at {RESONON_SAMPLES}")
    return RESONON_SAMPLES
