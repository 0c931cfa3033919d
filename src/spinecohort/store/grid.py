"""Model IDs of the virtual cohort's grid and the shards that cut it.

The grid holds every combination of ``n_modes`` mode weights drawn from ``levels`` (SD units): 7^5 =
16,807 models by default.  A model ID is the mixed-radix number of its SD-level indices, mode 1 most
significant (``model_id = sum_i (w_i + 3) * 7^(5 - i)`` on the default 5 x {-3..3} grid); a shard is the
contiguous ID range ``[shard * shard_models, (shard + 1) * shard_models)``.
"""

from __future__ import annotations

import numpy as np

#: SD levels of the default grid and number of modes (5 x {-3..3} -> 16,807 models).
DEFAULT_LEVELS = (-3, -2, -1, 0, 1, 2, 3)
DEFAULT_N_MODES = 5
DEFAULT_SHARD_MODELS = 2401


def _levels_array(levels) -> np.ndarray:
    lv = np.asarray(levels, dtype=np.float64)
    if lv.ndim != 1 or lv.size < 1:
        raise ValueError(f"levels must be a non-empty 1-D sequence of SD values, got {levels!r}")
    if np.any(np.diff(lv) <= 0):
        raise ValueError(f"levels must be strictly increasing, got {list(lv)}")
    return lv


def n_models(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> int:
    """Number of models on the grid: len(levels) ** n_modes (7^5 = 16,807 by default)."""
    if n_modes < 1:
        raise ValueError(f"n_modes must be >= 1, got {n_modes}")
    return len(_levels_array(levels)) ** int(n_modes)


def model_id(weights, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Model IDs of grid weights (..., n_modes) in SD units; mode 1 is the most significant digit.

    On the default grid this is ``sum_i (w_i + 3) * 7^(n_modes - i)``.  Weights must lie on the grid.
    """
    lv = _levels_array(levels)
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim < 1:
        raise ValueError("weights must have a trailing mode axis")
    digit = np.searchsorted(lv, w)
    digit_c = np.clip(digit, 0, lv.size - 1)
    if np.any(np.abs(lv[digit_c] - w) > 1e-9) or np.any(digit >= lv.size):
        raise ValueError(f"weights off the grid levels {list(lv)}")
    place = lv.size ** np.arange(w.shape[-1] - 1, -1, -1, dtype=np.int64)
    return digit_c.astype(np.int64) @ place


def weights_of(ids, n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """Grid weights (..., n_modes) in SD units of model IDs (...); inverse of :func:`model_id`."""
    lv = _levels_array(levels)
    i = np.asarray(ids)
    if not np.issubdtype(i.dtype, np.integer):
        raise ValueError(f"model IDs must be integers, got dtype {i.dtype}")
    total = lv.size ** int(n_modes)
    if np.any(i < 0) or np.any(i >= total):
        raise ValueError(f"model IDs must lie in [0, {total}), got range [{i.min()}, {i.max()}]")
    place = lv.size ** np.arange(n_modes - 1, -1, -1, dtype=np.int64)
    digits = (i.astype(np.int64)[..., None] // place) % lv.size
    return lv[digits]


def grid_weights(n_modes: int = DEFAULT_N_MODES, levels=DEFAULT_LEVELS) -> np.ndarray:
    """All grid weights (n_models, n_modes) in SD units, row k = weights of model k."""
    return weights_of(np.arange(n_models(n_modes, levels)), n_modes, levels)


def model_name(ids) -> list[str] | str:
    """``model_00000``-style names of one ID or an array of IDs."""
    if np.ndim(ids) == 0:
        return f"model_{int(ids):05d}"
    return [f"model_{int(k):05d}" for k in np.ravel(ids)]


def n_shards(total_models: int, shard_models: int = DEFAULT_SHARD_MODELS) -> int:
    """Number of shards covering total_models IDs (the last one may be partial)."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    return -(-int(total_models) // int(shard_models))


def shard_range(
    shard: int, shard_models: int = DEFAULT_SHARD_MODELS, total_models: int | None = None
) -> tuple[int, int]:
    """Half-open model-ID range [start, stop) of ``shard``; clipped to total_models when given."""
    if shard_models < 1:
        raise ValueError(f"shard_models must be >= 1, got {shard_models}")
    if shard < 0 or (total_models is not None and shard >= n_shards(total_models, shard_models)):
        raise ValueError(f"shard {shard} out of range for {total_models} models in shards of {shard_models}")
    start = int(shard) * int(shard_models)
    stop = start + int(shard_models)
    return start, stop if total_models is None else min(stop, int(total_models))
