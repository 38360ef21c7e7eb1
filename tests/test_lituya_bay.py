"""The Lituya Bay showcase, scenes/lituya_bay.toml (a 1:675 rock slide into a fjord-like inlet, after Fritz, Hager &
Minor 2001), at a coarse spacing for a fraction of a second: on the dry slope the six slide blocks keep their launch
speed and follow the Coulomb friction law s = v0 t + a t^2 / 2, a = g (sin 40 - tan 25 cos 40), read from the hazard
summary's slide motion; with the water (from the CLI, USD on) the water stays in the inlet, the slide entering it is
slowed below the dry law, the gauges and the run-up lines on the opposite shore read finite values, and the preview's
frame strip draws the run."""

import json
import math
import subprocess
import sys
import tomllib

import numpy as np
import pytest

import rockwave
from rockwave.app.preview import PreviewError, render_strip, strip_frames
from rockwave.output.hazard import HazardMonitor
from rockwave.scene.format import parse_scene

from conftest import DEVICE
from helpers import ROOT, to_toml

G = 9.81
THETA = math.radians(40.0)
SCENE = ROOT / "scenes" / "lituya_bay.toml"
COARSE_M = 0.06  # ~3,000 water particles (the shipped 0.009 m: 0.88 M)
V0 = 110.0 / math.sqrt(675.0)  # the prototype's impact speed at 1:675 (Froude): 4.234 m/s


def _scene(water: bool = True) -> dict:
    d = tomllib.loads(SCENE.read_text())
    d["fluid"]["spacing_m"] = COARSE_M
    if not water:
        for k in ("fluid", "tank", "coupling"):
            d.pop(k)
        d["output"].pop("gauges")
        d["hazard"] = {"sample_interval_s": 0.01,
                       "slides": [{"block": b["name"], "along": d["hazard"]["slides"][0]["along"]}
                                  for b in d["blocks"] if b["name"].startswith("slide_") and "slope" not in b["name"]]}
    return d


def _law(d: dict) -> float:
    phi = {b["name"]: b["material"]["friction_angle_deg"] for b in d["blocks"]}
    assert phi["slide_slope"] == phi["slide_back_0"]
    return G * (math.sin(THETA) - math.tan(math.radians(phi["slide_slope"])) * math.cos(THETA))


def test_dry_slide_keeps_its_launch_speed_and_follows_the_friction_law():
    """Without the water the six blocks slide down the 40 deg plane together: each one's speed along the slope at
    t = 0 is the launch speed 4.234 m/s and its displacement over 0.15 s fits v0 t + a t^2 / 2 with a = 2.80 m/s^2
    within 2% (the back blocks stay on the slope; the front ones leave it at its toe after ~0.07 s, so they are read
    until 0.06 s)."""
    d = _scene(water=False)
    law = _law(d)
    assert law == pytest.approx(2.801, abs=1e-3)
    sim = rockwave.Simulation(parse_scene(d, str(SCENE)), device=DEVICE)
    hz = HazardMonitor(sim)
    sim.advance(0.15, watch=hz.after_step)
    slides = hz.result()["slides"]
    assert len(slides) == 6
    for name, s in slides.items():
        m = s["motion"]
        t, x, v = (np.asarray(m[k]) for k in ("t_s", "along_m", "speed_along_m_s"))
        assert v[0] == pytest.approx(V0, rel=1e-3), name
        sel = t <= (0.15 if "back" in name else 0.06) + 1e-9
        c2, c1, _ = np.polyfit(t[sel], x[sel], 2)
        assert c1 == pytest.approx(V0, rel=0.01), name
        assert 2.0 * c2 == pytest.approx(law, rel=0.02), name
        c = np.asarray(m["centroid_m"])
        assert np.abs(c[sel, 1] - c[0, 1]).max() < 1e-4, name  # no drift across the slope


def test_slide_into_the_inlet_from_the_cli(tmp_path):
    """`python -m rockwave run` at 0.06 m for 0.2 s with USD frames: every water particle stays in the inlet, the
    front blocks, in the water by then, are slowed below the dry slope's law (measured 0.57 m against 0.90 m), every
    gauge and run-up line of hazard.json reads a finite value (at this spacing the x = 0.5 m gauge a 0.22 m crest and
    a trough to the floor behind the slide; the run-up lines, 0.2 s before the wave reaches them, the still shore), and `preview --strip 3` draws the first, middle and last frames in one PNG."""
    d = _scene()
    d["output"]["frame_rate_hz"] = 10.0
    scene = tmp_path / "lituya_coarse.toml"
    scene.write_text(to_toml(d))
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "rockwave", "run", str(scene), "--out", str(out), "--duration", "0.2",
                        "--device", DEVICE, "--quiet", "--yes"], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    hz = json.loads((out / "hazard.json").read_text())
    assert set(hz["gauges"]) == {"x0.5", "x1.0", "x1.5", "x1.0_y0.6"}
    for name, g in hz["gauges"].items():
        for k in ("max_crest_m", "deepest_trough_m"):
            assert g[k] is not None and math.isfinite(g[k]) and -0.181 - COARSE_M <= g[k] < 0.6, (name, k, g[k])
    assert set(hz["runup"]) == {"runup_y0", "runup_y0.4", "runup_y0.8"}
    for name, ru in hz["runup"].items():
        assert math.isfinite(ru["max_runup_m"]) and -0.1 < ru["max_runup_m"] < 1.0, (name, ru["max_runup_m"])
    law = _law(d)
    for name in ("slide_front_0", "slide_front_1"):
        m = hz["slides"][name]["motion"]
        t, x = np.asarray(m["t_s"]), np.asarray(m["along_m"])
        dry = V0 * t[-1] + 0.5 * law * t[-1] ** 2
        assert 0.3 * dry < x[-1] < dry - 0.01, (name, x[-1], dry)
    # the water stays in the inlet: the last frame's particles inside the tank (a spacing of slack)
    from rockwave.app.preview import load_frame

    f = load_frame(out)
    lo, hi = np.asarray(d["tank"]["box_min_m"]), np.asarray(d["tank"]["box_max_m"])
    assert len(f["x"]) > 1000
    assert np.all(f["x"] >= lo - COARSE_M) and np.all(f["x"] <= hi + COARSE_M)
    assert f["time_s"] == pytest.approx(0.2)
    first, last = f["frames"]
    assert strip_frames(first, last, 3) == [first, (first + last) // 2, last]
    r = subprocess.run([sys.executable, "-m", "rockwave", "preview", str(out), "--strip", "3", "--out", str(tmp_path / "strip.png")],
                       capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "strip.png").stat().st_size > 10_000
    with pytest.raises(PreviewError):
        render_strip(out, 0)
