"""DualSPHysics 5.0 side by side with rockwave on SPHERIC Test 2 (issue 19): same case, spacing, duration
and GPU, gauge errors scored by one function (benchmarks/harness.py ``spheric_errors``).

DualSPHysics is not installed with rockwave (LGPL, C++/CUDA: built from source on the GPU machine
with its own build scripts). Its SPHERIC Test 2 case file comes from the DualSPHysics performance-test
repository (``test_linux/_DataCases_Ds5Test/Spheric2Dam_400K.xml``); this module never ships that file,
it rewrites a copy the user gives it:

    python -m benchmarks.peers.dualsphysics case SRC.xml OUT_def.xml --dp 0.012 --hdp 2 --t-end 1.5
        -> the case at spacing dp with smoothing length h = hdp dp (Wendland support 2 h), duration t-end,
           and four free-surface gauges (``<swl>``) at the experiment's H1-H4 (x = 0.496, 0.992, 1.488,
           2.638 m, y = 0.5 m): each reads the top of the continuous water column from the bed (the first
           point up the vertical line where the kernel-summed fluid mass drops below half a particle's),
           the same definition as rockwave's height gauge;
    GenCase_linux64 OUT_def DIR/Spheric2Dam -save:all
    DualSPHysics_linux64 -gpu:0 DIR/Spheric2Dam DIR -dirdataout data -sv:none -svres
    python -m benchmarks.peers.dualsphysics score DIR --wall-s SECONDS
        -> GaugesSWL_H*.csv resampled at rockwave's gauge times (every 0.01 s), errors as rockwave's.

Everything else is the case's own setting (its "standard settings"): symplectic, Wendland, dynamic
boundary particles (DBC), artificial viscosity 0.004 (not on walls), Fourtakas (2019) density diffusion 0.1,
CFL 0.2, c0 = 20 x the dam-break speed.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path

import numpy as np

# the experiment's water-level gauges (Kleefsman et al. 2005), as in scenes/dam_break_3d.toml
GAUGES = {"H1": 0.496, "H2": 0.992, "H3": 1.488, "H4": 2.638}


def case_xml(src: str, dp: float, hdp: float, t_end: float) -> str:
    """The case text ``src`` at spacing ``dp``, h/dp = ``hdp``, TimeMax ``t_end`` and with the H1-H4 gauges."""
    out, n = re.subn(r'(<definition dp=")[^"]*(")', rf"\g<1>{dp:g}\g<2>", src)
    if n != 1:
        raise ValueError("no <definition dp=...> in the case file")
    out, n = re.subn(r'(<hdp value=")[^"]*(")', rf"\g<1>{hdp:g}\g<2>", out)
    if n != 1:
        raise ValueError("no <hdp value=...> in the case file")
    out, n = re.subn(r'(<parameter key="TimeMax" value=")[^"]*(")', rf"\g<1>{t_end:g}\g<2>", out)
    if n != 1:
        raise ValueError("no TimeMax parameter in the case file")
    g = ['        <special>', '            <gauges>', '                <default>',
         '                    <computedt value="0.01" />', '                    <output value="true" />',
         '                    <outputdt value="0.01" />', '                </default>']
    for name, x in GAUGES.items():
        g += [f'                <swl name="{name}">', f'                    <point0 x="{x}" y="0.5" z="{dp / 2:g}" />',
              f'                    <point2 x="{x}" y="0.5" z="1.0" />', '                    <pointdp coefdp="0.5" />',
              '                </swl>']
    g += ['            </gauges>', '        </special>', '    </execution>']
    if out.count("</execution>") != 1:
        raise ValueError("no single </execution> in the case file")
    return out.replace("    </execution>", "\n".join(g))


def read_gauge(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(times, heights) of one GaugesSWL csv; a dry line (the level at its lowest point) reads 0."""
    rows = [ln.split(";") for ln in path.read_text().splitlines()[1:] if ln.strip()]
    a = np.array([[float(r[0]), float(r[3]), float(r[6])] for r in rows])
    h = np.where(a[:, 1] <= a[:, 2] + 1e-9, 0.0, a[:, 1])
    return a[:, 0], h


def score(folder: Path, wall_s: float | None = None, sample_dt: float = 0.01) -> dict:
    """Errors of a DualSPHysics run's gauges (``folder`` holds GaugesSWL_H1..H4.csv), resampled at rockwave's
    gauge times, and its wall seconds per simulated second when ``wall_s`` is given."""
    from benchmarks.harness import spheric_errors

    series = {n: read_gauge(folder / f"GaugesSWL_{n}.csv") for n in GAUGES}
    t_end = min(float(t[-1]) for t, _ in series.values())
    ts = np.arange(sample_dt, t_end + 1e-9, sample_dt)
    gauges = {n: np.interp(ts, t, h) for n, (t, h) in series.items()}
    rec = spheric_errors(ts, gauges)
    rec["simulated_s"] = float(ts[-1])
    if wall_s is not None:
        rec["wall_s"] = wall_s
        rec["wall_per_sim_s"] = wall_s / t_end
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in rec.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.peers.dualsphysics", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("case", help="rewrite DualSPHysics's Spheric2Dam case XML")
    c.add_argument("src")
    c.add_argument("out")
    c.add_argument("--dp", type=float, default=0.012)
    c.add_argument("--hdp", type=float, default=2.0)
    c.add_argument("--t-end", type=float, default=1.5)
    s = sub.add_parser("score", help="gauge errors of a finished run")
    s.add_argument("folder")
    s.add_argument("--wall-s", type=float, default=None)
    a = ap.parse_args(argv)
    if a.cmd == "case":
        Path(a.out).write_text(case_xml(Path(a.src).read_text(), a.dp, a.hdp, a.t_end))
    else:
        print(json.dumps(score(Path(a.folder), a.wall_s), indent=1))


if __name__ == "__main__":
    main()
