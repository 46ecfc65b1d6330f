"""Shared references of the hysteresis tests."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest


def _relay_loop(u, alpha, beta, s0) -> np.ndarray:
    """Hysteron-by-hysteron, step-by-step exact relays in float64 Python.

    Takes numpy arrays or torch tensors (1D: inputs ``u`` (T,), thresholds
    ``alpha``, ``beta`` and initial states ``s0`` (M,)); returns the relay
    states ``(T, M)`` as a float64 numpy array. Ties switch: ``u == alpha`` up,
    ``u == beta`` down.
    """
    out = np.empty((len(u), len(alpha)))
    for i, (a, b) in enumerate(zip(alpha.tolist(), beta.tolist(), strict=True)):
        s = float(s0[i])
        for t, ut in enumerate(u.tolist()):
            if ut >= a:
                s = 1.0
            elif ut <= b:
                s = -1.0
            out[t, i] = s
    return out


@pytest.fixture
def relay_loop() -> Callable[..., np.ndarray]:
    """The independent relay-by-relay reference (see :func:`_relay_loop`)."""
    return _relay_loop
