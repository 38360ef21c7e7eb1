"""Device names: 'auto', 'cpu', 'cuda' or 'cuda:N'. The syntax check needs no Warp (the scene loader
uses it); :func:`resolve_device` also checks that the device exists."""

from __future__ import annotations

import os
import re
import sys
import tempfile

# What Warp's native library prints (C stdio, file descriptor 2, so neither config.quiet nor config.log_level
# stops it) while it looks for a GPU on a machine without one: an expected note, not an error.
NO_DRIVER_NOTE = "Could not find or load the NVIDIA CUDA driver"

DEVICE_SYNTAX = re.compile(r"(auto|cpu|cuda|cuda:[0-9]+)")
ALLOWED = "auto, cpu, cuda or cuda:N (N = 0, 1, ...)"


class DeviceError(ValueError):
    """A device name that is malformed or names a device this machine does not have."""


class WarpCacheError(RuntimeError):
    """Warp's kernel cache folder cannot be created or written (Warp makes it in ``wp.init()``; WARP_CACHE_PATH
    chooses it). The message names the folder and how to choose another."""


def _cache_error(folder, why: str) -> WarpCacheError:
    env = os.environ.get("WARP_CACHE_PATH")
    how = (f"WARP_CACHE_PATH={env!r} chose it: set WARP_CACHE_PATH to a writable folder" if env else
           "set WARP_CACHE_PATH to a writable folder, e.g. WARP_CACHE_PATH=/tmp/warp-cache python -m rockwave ...")
    return WarpCacheError(f"Warp's kernel cache folder {folder} {why}; {how}")


def _wp_init(wp) -> None:
    """wp.init(), with a kernel cache folder that cannot be made or written reported as a WarpCacheError."""
    try:
        wp.init()
    except OSError as e:
        folder = getattr(wp.config, "kernel_cache_dir", None) or os.environ.get("WARP_CACHE_PATH")
        if folder is None:
            raise
        raise _cache_error(folder, f"cannot be created ({e.strerror or e}{': ' + str(e.filename) if e.filename else ''})") from None
    folder = getattr(wp.config, "kernel_cache_dir", None)
    if folder and os.path.isdir(folder) and not os.access(folder, os.W_OK | os.X_OK):
        raise _cache_error(folder, "is not writable (Warp writes the compiled kernels there)")


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

    init_warp()
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


def _warp_quiet(wp) -> bool:
    if getattr(wp.config, "quiet", False):
        return True
    level, error = getattr(wp.config, "log_level", None), getattr(wp, "LOG_ERROR", None)
    return level is not None and error is not None and level >= error


def init_warp(quiet: bool | None = None) -> None:
    """``wp.init()``; when quiet (default: when Warp is configured quiet, rockwave.app.cli.quiet_warp) Warp's
    native library prints nothing either: file descriptor 2 goes to a temporary file for the call (the
    "no CUDA driver" note of a machine without a GPU is written there by C code, which Warp's settings do
    not reach). Whatever else lands there is written back to stderr afterwards, and if the init fails all of
    it is, before the exception goes on: a real error stays visible. A no-op once Warp is initialised."""
    import warp as wp

    if quiet is None:
        quiet = _warp_quiet(wp)
    if not quiet:
        _wp_init(wp)
        return
    try:
        for s in (sys.stdout, sys.stderr, sys.__stderr__):
            if s is not None:
                s.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no usable descriptor 2 (an embedding host): plain init
        _wp_init(wp)
        return
    failed = False
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            _wp_init(wp)
        except WarpCacheError:  # (said in the error)
            raise
        except BaseException:
            failed = True
            raise
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError, AttributeError):
                pass
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
            keep = text if failed else "".join(l for l in text.splitlines(True) if NO_DRIVER_NOTE not in l)
            if keep.strip():
                sys.stderr.write(keep if keep.endswith("\n") else keep + "\n")
                sys.stderr.flush()


def quiet_warp(init: bool = True) -> None:
    """No Warp banner, module-load lines or driver notes (set before wp.init(); Warp >= 1.19 reads
    config.log_level, older versions config.quiet), then (``init``) Warp's init with its native library's stderr held
    back (rockwave.base.device.init_warp: the "no CUDA driver" note that C code prints on a machine without a GPU;
    anything else it prints, and everything when the init fails, is shown). ``init=False``: the settings only (a
    command that needs no kernels never initialises Warp, so never makes its kernel cache folder; resolve_device
    initialises it quietly when a device is first needed)."""
    import warp as wp

    wp.config.quiet = True
    if hasattr(wp, "LOG_ERROR"):
        wp.config.log_level = wp.LOG_ERROR
    if init:
        init_warp(quiet=True)
