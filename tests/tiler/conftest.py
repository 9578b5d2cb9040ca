"""Fixtures shared by the tiler's kernel tests."""

from __future__ import annotations

import pytest

from tiler import kernels


@pytest.fixture
def numba_backend(monkeypatch):
    """The compiled kernels for this test (``TERRASTREAM_KERNELS=numba``)."""
    monkeypatch.setenv(kernels.ENV, "numba")
    assert kernels.backend() == "numba"
