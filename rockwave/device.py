"""Device names: 'auto', 'cpu', 'cuda' or 'cuda:N'. The syntax check needs no Warp (the scene loader
uses it); :func:`resolve_device` also checks that the device exists."""

from __future__ import annotations

import re

DEVICE_SYNTAX = re.compile(r"(auto|cpu|cuda|cuda:[0-9]+)")
ALLOWED = "auto, cpu, cuda or cuda:N (N = 0, 1, ...)"


class DeviceError(ValueError):
    """A device name that is malformed or names a device this machine does not have."""


def device_syntax_error(name) -> str | None:
    """Why ``name`` is not a device name (None when it is one). Needs no Warp."""
    if not isinstance(name, str):
        return f"expected a string ({ALLOWED}), got {type(name).__name__} {name!r}"
    if DEVICE_SYNTAX.fullmatch(name):
        return None
    hint = ""
    low = name.strip().lower()
    if low != name and DEVICE_SYNTAX.fullmatch(low):
        hint = f"; did you mean {low!r}?"
    elif low in ("gpu", "cuda0") or low.startswith("gpu"):
        hint = "; for a GPU write 'cuda' or 'cuda:0'"
    return f"{name!r} is not a device name; expected {ALLOWED}{hint}"


def resolve_device(name: str | None) -> str:
    """'auto' -> 'cuda:0' when a GPU is present, else 'cpu'. Validates explicit names and that the
    device exists; raises :class:`DeviceError` (a ValueError) with a one-line reason."""
    name = "auto" if name is None else name
    why = device_syntax_error(name)
    if why:
        raise DeviceError(why)
    import warp as wp

    wp.init()
    n = wp.get_cuda_device_count()
    if name == "auto":
        return "cuda:0" if n > 0 else "cpu"
    if name == "cpu":
        return "cpu"
    idx = 0 if name == "cuda" else int(name.split(":", 1)[1])
    if idx >= n:
        have = "no CUDA device" if n == 0 else f"{n} CUDA device(s): cuda:0" + (f" .. cuda:{n - 1}" if n > 1 else "")
        raise DeviceError(f"{name!r}: this machine has {have}; use 'cpu' or 'auto'")
    return f"cuda:{idx}"
