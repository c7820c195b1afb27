"""Device and precision names (``"cuda:1"``, ``"float64"``) as torch objects, checked once here
for every configuration, command option and constructor that takes them; and the one way a
tensor (any device) becomes a host array, :func:`to_numpy`."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

__all__ = ["DTYPES", "torch_dtype", "resolve_device", "to_numpy"]

#: the precisions a configuration may name
DTYPES: dict[str, torch.dtype] = {"float32": torch.float32, "float64": torch.float64}


def torch_dtype(name: str | torch.dtype) -> torch.dtype:
    """``"float32"`` / ``"float64"`` (a configuration's ``dtype``; a torch dtype passes) → the
    torch dtype.

    Raises:
        ValueError: another name.
    """
    if isinstance(name, torch.dtype):
        return name
    try:
        return DTYPES[name]
    except (KeyError, TypeError):
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, got {name!r}") from None


def resolve_device(
    name: str | torch.device | None, label: str = "device", here: bool = True
) -> torch.device:
    """``name`` as a torch device (``None``: the CPU), refused with a ``ValueError`` that names
    it (``label``: how the caller calls it, e.g. ``"--device"`` or ``"config key 'device'"``)
    when torch does not know it or, with ``here``, when this machine lacks it (CUDA or MPS not
    available, a CUDA index beyond the devices present) — not torch's own ``RuntimeError`` /
    ``AssertionError`` from deep inside the work."""
    if name is None:
        return torch.device("cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{label} {str(name)!r}: not a torch device ({first})") from None
    if not here:
        return dev
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{label} {str(name)!r}: CUDA is not available on this machine/torch "
                         "build")  # fmt: skip
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"{label} {str(name)!r}: this machine has {torch.cuda.device_count()} "
                         "CUDA device(s)")  # fmt: skip
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"{label} {str(name)!r}: MPS is not available on this machine/torch "
                         "build")  # fmt: skip
    return dev


def to_numpy(x: Any, dtype: Any = None) -> np.ndarray:
    """A tensor (any device; detached, copied to the host) or an array-like as a numpy array
    (shared with ``x`` where possible), in ``dtype`` if given (a copy only where it differs)."""
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    return a if dtype is None else a.astype(dtype, copy=False)
