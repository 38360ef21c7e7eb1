"""Part ``stability``: stability maps. Fluid: the 2D dam break at dt = k x the CFL step for each
speed of sound c0 and method; blocks: a 3-cube stack at dt = k x the critical DDA step for each contact
stiffness k_n. Every run is classified by benchmarks/harness.py (stable, inaccurate, blown_up, refused)."""

from __future__ import annotations

from benchmarks import harness as H
from benchmarks.common import log

_SWEEP = dict(stab_t_end=0.12, stab_mult=[0.5, 1, 2, 4, 8, 16], stab_c0=[5, 10, 20, 40, 80],
              stab_methods=["tait", "linear", "ghost"], blk_k=[1e6, 1e7, 1e8, 1e9, 1e10], blk_mult=[0.25, 0.5, 1.0, 2.0],
              blk_t_end=0.3)
CONFIG = {"quick": dict(stab_res=10, **_SWEEP), "full": dict(stab_res=20, **_SWEEP)}


def run(dev: str, cfg: dict) -> dict:
    out = {"fluid": [], "blocks": []}
    n = cfg["stab_res"]
    for m in cfg["stab_methods"]:
        H.run_dam_break(dev, H.A_MM / n, H.VARIANTS[m], 0.002)
        for c0 in cfg["stab_c0"]:
            for k in cfg["stab_mult"]:
                r = H.run_dam_break(dev, H.A_MM / n, H.VARIANTS[m], cfg["stab_t_end"], dt_multiple=k, c0=c0)
                r.update(method=m, c0=c0, dt_multiple=k)
                r["class"], r["why"] = H.classify(r)
                out["fluid"].append(r)
        row = " ".join(f"{r['class'][:4]}" for r in out["fluid"] if r["method"] == m)
        log(f"  fluid stability {m:8s} ({len(cfg['stab_c0'])} c0 x {len(cfg['stab_mult'])} dt): {row}")
    for kn in cfg["blk_k"]:
        for k in cfg["blk_mult"]:
            r = H.run_block_stack(dev, kn, k, cfg["blk_t_end"])
            r["class"], r["why"] = H.classify(r)
            out["blocks"].append(r)
    log("  block stability: " + " ".join(r["class"][:4] for r in out["blocks"]))
    return out
