"""Shared test configuration: float64 everywhere and the path to the shared real tracks."""

from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

SHARED_TRACKS = Path(__file__).resolve().parents[1].parent / "shared" / "tracks"


@pytest.fixture(scope="session")
def shared_tracks() -> Path:
    if not SHARED_TRACKS.is_dir():
        pytest.skip(f"real track files not found at {SHARED_TRACKS}")
    return SHARED_TRACKS
