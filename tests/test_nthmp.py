"""The NTHMP landslide benchmark 3 scenes (Liu et al. 2005: a rigid wedge down a 1:2 slope into still water),
scenes/nthmp_slide_subaerial.toml and nthmp_slide_submarine.toml, at a coarse spacing for a fraction of a second:
they build, the wedge on the dry slope follows the Coulomb friction law a = g (sin theta - Cn cos theta) read
from the hazard summary's slide motion, and with the water the gauges read finite values, the water slows the
wedge, and the CLI writes the motion (slide_motion.csv)."""

import csv
import json
import math
import subprocess
import sys
import tomllib

import numpy as np
import pytest

import rockwave
from rockwave.output.hazard import HazardMonitor
from rockwave.scene.format import parse_scene

from conftest import DEVICE
from helpers import ROOT, to_toml

G = 9.81
THETA = math.atan(0.5)  # the 1:2 slope
COARSE_M = 0.2  # spacing of the tests: ~3,700 particles (the shipped 0.025 m: ~2 M)


def _scene(kind: str, water: bool = True) -> dict:
    path = ROOT / "scenes" / f"nthmp_slide_{kind}.toml"
    d = tomllib.loads(path.read_text())
    d["fluid"]["spacing_m"] = COARSE_M
    if not water:
        for k in ("fluid", "tank", "coupling"):
            d.pop(k)
        d["hazard"] = {"sample_interval_s": 0.01, "slides": d["hazard"]["slides"]}
        d["output"].pop("gauges")
    return d


def _law(d: dict) -> float:
    """g (sin theta - Cn cos theta), Cn = tan of the wedge's friction angle (the slope's is the same)."""
    mats = {b["name"]: b["material"]["friction_angle_deg"] for b in d["blocks"]}
    assert mats["wedge"] == mats["slope"]
    return G * (math.sin(THETA) - math.tan(math.radians(mats["wedge"])) * math.cos(THETA))


def _fit_acceleration(m: dict, t_min: float = 0.02) -> float:
    """2 c2 of the least-squares parabola s(t) = c0 + c1 t + c2 t^2 through the motion's down-slope displacement."""
    t, s = np.asarray(m["t_s"]), np.asarray(m["along_m"])
    sel = t > t_min
    return 2.0 * float(np.polyfit(t[sel], s[sel], 2)[0])


@pytest.mark.parametrize("kind", ["subaerial", "submarine"])
def test_dry_wedge_follows_the_friction_law(kind):
    """Without the water the wedge slides down the 1:2 plane with a = g (sin theta - Cn cos theta) (Cn = 0.1577:
    3.003 m/s^2) within 0.5% over 0.3 s (measured -3e-6 relative), read from hazard.json's slide motion: the
    displacement along the slope's down direction and the speed along it (v = a t within 0.5%)."""
    d = _scene(kind, water=False)
    sim = rockwave.Simulation(parse_scene(d, str(ROOT / "scenes" / f"nthmp_slide_{kind}.toml")), device=DEVICE)
    hz = HazardMonitor(sim)
    sim.advance(0.3, watch=hz.after_step)
    m = hz.result()["slides"]["wedge"]["motion"]
    assert len(m["t_s"]) == 31 and np.all(np.diff(m["t_s"]) > 0)
    law = _law(d)
    assert law == pytest.approx(3.003, abs=1e-3)
    assert _fit_acceleration(m) == pytest.approx(law, rel=5e-3)
    t, v = np.asarray(m["t_s"]), np.asarray(m["speed_along_m_s"])
    assert v[-1] == pytest.approx(law * t[-1], rel=5e-3)
    # the motion is along the slope: the centroid's drop is the displacement times sin theta
    c = np.asarray(m["centroid_m"])
    assert c[0, 2] - c[-1, 2] == pytest.approx(m["along_m"][-1] * math.sin(THETA), rel=1e-3)
    assert abs(c[-1, 1] - c[0, 1]) < 1e-4  # no drift across the slope


def test_subaerial_run_from_the_cli_reads_finite_gauges_and_writes_the_motion(tmp_path):
    """`python -m rockwave run` on the subaerial scene at 0.2 m for 0.3 s: every wave gauge of hazard.json reads
    a finite crest and trough (the wedge is not yet under the centre-line gauge), slide_motion.csv holds the
    wedge's motion every 0.01 s, and the water slows the wedge below the dry slope's law (buoyancy alone takes
    16% of its weight: 61% of the wedge starts under water), measured 2.10 against 3.00 m/s^2."""
    d = _scene("subaerial")
    scene = tmp_path / "nthmp_coarse.toml"
    scene.write_text(to_toml(d))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "rockwave", "run", str(scene), "--out", str(out), "--duration", "0.3",
                        "--device", DEVICE, "--quiet", "--yes"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    hz = json.loads((out / "hazard.json").read_text())
    assert set(hz["gauges"]) == {"x1.2b_y0", "x1.2b_y0.5b", "x1.2b_y1b", "x1.2b_y1.5b", "x2b_y0"}
    for name, g in hz["gauges"].items():
        for k in ("max_crest_m", "deepest_trough_m"):
            assert g[k] is not None and math.isfinite(g[k]) and abs(g[k]) < 0.3, (name, k, g[k])
    assert set(hz["runup"]) == {"runup_y0", "runup_y0.5b", "runup_y1b"}
    rows = list(csv.DictReader((out / "slide_motion.csv").open()))
    assert len(rows) == 31
    assert {"t_s", "wedge.x_m", "wedge.vz_m_s", "wedge.along_m", "wedge.speed_along_m_s"} <= set(rows[0])
    m = {"t_s": [float(r["t_s"]) for r in rows], "along_m": [float(r["wedge.along_m"]) for r in rows]}
    a = _fit_acceleration(m)
    assert 0.3 * _law(d) < a < 0.95 * _law(d)
    assert hz["slides"]["wedge"]["peak_speed_m_s"] == pytest.approx(float(rows[-1]["wedge.speed_along_m_s"]), rel=0.05)


def test_submarine_scene_builds_and_the_water_holds_the_wedge_back():
    """The submarine scene at 0.2 m for 0.2 s: the gauges off the slide's path read finite values (the centre-line
    one at x/b = 1.2 stands over the wedge's front at the start: 0.1 m of water over it, half a spacing, reads dry), and
    the wedge, wholly under water, accelerates slower than its buoyant weight alone would drive it,
    g (1 - rho_w/rho_b)(sin theta - Cn cos theta) = 2.21 m/s^2 (added mass and drag), measured 1.28."""
    d = _scene("submarine")
    sim = rockwave.Simulation(parse_scene(d, str(ROOT / "scenes" / "nthmp_slide_submarine.toml")), device=DEVICE)
    hz = HazardMonitor(sim)
    sim.advance(0.2, watch=hz.after_step)
    res = hz.result()
    for name in ("x1.2b_y0.5b", "x1.2b_y1b", "x1.2b_y1.5b", "x2b_y0"):
        g = res["gauges"][name]
        assert all(g[k] is not None and math.isfinite(g[k]) for k in ("max_crest_m", "deepest_trough_m")), (name, g)
    rho_b = next(b["density_kg_m3"] for b in d["blocks"] if b["name"] == "wedge")
    buoyant = (1.0 - 1000.0 / rho_b) * _law(d)
    a = _fit_acceleration(res["slides"]["wedge"]["motion"])
    assert 0.2 * buoyant < a < buoyant
