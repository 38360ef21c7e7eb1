"""Part ``peers``: peer codes run side by side with rockwave on the same problem: SPlisHSPlasH's WCSPH
on the CPU (benchmarks/peers/splash.py, worker splash_worker.py; the dam-break front measured the same way
in both codes, benchmarks/peers/front.py) and Warp's example_sph.py (benchmarks/peers/warp_example.py)."""

from __future__ import annotations

import traceback

from benchmarks.common import log

CONFIG = {"quick": dict(splash_res=10, warp_example_spacing=0.06), "full": dict(splash_res=10, warp_example_spacing=0.02)}


def run(dev: str, cfg: dict) -> dict:
    from benchmarks.peers import splash, warp_example

    out = {}
    try:
        out["splash"] = splash.compare(cfg["splash_res"], device=dev)  # runs on the CPU whatever the suite's device
        s = out["splash"]
        log(f"  SPlisHSPlasH: {s.get('splash', {}).get('skipped') or 'ran'}; ratio {s.get('throughput_ratio')}")
    except Exception as e:  # recorded; the Warp example still runs
        out["splash"] = {"error": f"{type(e).__name__}: {e}"[:300], "trace": traceback.format_exc()[-800:]}
        log(f"  SPlisHSPlasH comparison failed: {out['splash']['error']}")
    try:
        out["warp_example"] = w = warp_example.compare(cfg["warp_example_spacing"], dev)
        log(f"  Warp example_sph at {w['warp_example']['particles']} particles ({w['warp_example']['neighbours']:.1f} nbrs): "
            f"{w['warp_example']['particle_steps_per_s']:.3g} particle-steps/s; rockwave "
            f"{w['rockwave']['particle_steps_per_s']:.3g} ({w['rockwave']['neighbours']:.1f} nbrs); "
            f"ratio {w['throughput_ratio']:.2f}")
    except Exception as e:
        out["warp_example"] = {"error": f"{type(e).__name__}: {e}"[:300]}
        log(f"  Warp example failed: {out['warp_example']['error']}")
    return out
