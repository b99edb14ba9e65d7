"""Shared test fixtures: where the real datasets live.

The datasets are not in the repository: they sit in ``../shared/datasets`` beside the clone
(or where ``IOTNAV_DATASETS`` points). Tests that need them fail, not skip, when they are
missing, since real data is part of the test suite.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def datasets_dir() -> Path:
    """The shared datasets folder."""
    env = os.environ.get("IOTNAV_DATASETS")
    if env:
        return Path(env)
    return REPO.parent / "shared" / "datasets"


@pytest.fixture(scope="session")
def datasets() -> Path:
    """Path of ``../shared/datasets``; fails loudly when it is missing."""
    d = datasets_dir()
    if not d.is_dir():
        pytest.fail(f"real datasets not found at {d}; set IOTNAV_DATASETS")
    return d
