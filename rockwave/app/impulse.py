"""Scene makers for scenario studies: a study file's ``[study] generator = NAME`` builds each scenario's scene
from a few physical numbers instead of editing a base scene (rockwave/app/sweep.py). Each maker has
``PARAMS`` (name -> default; None: required), ``scene(params) -> (scene TOML dict, setup dict)`` and
``compare(setup, summary) -> flat columns`` (run after each scenario; the columns join the study table).

``impulse_2d``: the 2D impulse-wave channel of Heller & Hager (2010) and the VAW manual (Heller, Hager & Minor
2009): a rigid block slides down a plane of angle alpha into still water of depth h in a long channel and
raises an impulse wave; wave gauges every ``gauge_step`` h along the channel floor read its crest and trough
(rockwave/output/hazard.py); rockwave/output/impulse.py compares a_M, H_M, x_M and H(x) with the relations on the
impulse product parameter P. The slide is set by its dimensionless numbers:

- ``froude`` F = V_s / (g h)^(1/2): the block starts with its lower front corner at the still shoreline moving down
  the plane at V_s (as the laboratory's pneumatic launchers give the slide its impact speed); the basal friction
  angle equals the slope angle, so in the air it keeps V_s (driving and friction forces cancel) and the water alone
  slows it;
- ``thickness`` S = s / h;
- ``mass`` M = m_s / (rho_w b h^2) = D l s / h^2 per unit width, with D = ``density_ratio`` (rho_s / rho_w): the
  block's length along the slope is l = M h / (D S); a block with l/s < tan(alpha) would tip over its front edge
  (the base friction that balances gravity acts below its centroid) and is refused;
- ``slope_deg`` alpha;
- ``front_deg``: the angle between the slide's front face and its base (default 90: a box, whose front face at
  alpha < 90 deg leans forward over the water by s sin(alpha)); below 90 the slide is a trapezoid of the same
  thickness and area (its base lengthened by s / (2 tan(front))), so F, S, M and P do not change. The
  relations carry no slide shape, and a rigid block's near-field wave depends on it (docs/validation.md);
- ``layers``: particles per water depth (the resolution: spacing = h / layers).

The channel (its floor a fixed block, the tank around it) runs from the impact point (the still shoreline, x = 0) to
``gauge_max`` h plus room for the wave's
reflection from the end wall not to reach the last gauge within the run: end wall at x = gauge_max h + 2 h +
l / F; duration: the slide's entry l / V_s plus (gauge_max + 3) (h/g)^(1/2) (the wave's travel to the last gauge at
the shallow-water speed and about half a period).
"""

from __future__ import annotations

import math

from rockwave.output.impulse import G, compare_channel

Z_DEPTH = 0.1  # 2D blocks are prisms extruded this far along z (their z-extent; rockwave/coupling/penalty.py)


class ImpulseChannel2D:
    """The ``impulse_2d`` scene maker (module docstring)."""

    name = "impulse_2d"
    version = 2  # part of each scenario's hash: a change of the geometry below re-runs the scenarios
    PARAMS = {"froude": None, "thickness": None, "mass": None, "slope_deg": None, "layers": 16, "depth_m": 0.2,
              "density_ratio": 2.0, "gauge_step": 0.5, "gauge_min": 2.0, "gauge_max": 15.0,
              "normal_stiffness_n_m": 1.0e6, "fidelity": "standard", "block_walls": True,
              "sound_speed_factor": 10.0, "front_deg": 90.0}

    @classmethod
    def check(cls, params: dict, partial: bool = False) -> list[tuple[str, str]]:
        """(key, problem) for each missing (unless ``partial``: the study's fixed part), unknown or bad parameter."""
        bad = []
        for k, v in params.items():
            if k not in cls.PARAMS:
                bad.append((k, f"not a parameter of {cls.name}; allowed: {', '.join(cls.PARAMS)}"))
        for k, d in cls.PARAMS.items():
            v = params.get(k, d)
            if v is None:
                if not partial:
                    bad.append((k, f"required by {cls.name} (in [generator] or a [[vary]] key)"))
            elif k == "fidelity":
                if not isinstance(v, str):
                    bad.append((k, f"expected a fluid.fidelity name, got {v!r}"))
            elif k == "block_walls":
                if not isinstance(v, bool):
                    bad.append((k, f"expected true or false, got {v!r}"))
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                bad.append((k, f"expected a positive number, got {v!r}"))
        if not bad and params.get("slope_deg") is not None:
            a = float(params.get("slope_deg"))
            if not 5.0 <= a <= 85.0:
                bad.append(("slope_deg", f"{a:g}: a slope between 5 and 85 degrees"))
        if not bad and float(params.get("layers", cls.PARAMS["layers"])) < 4:
            bad.append(("layers", "at least 4 particles per depth"))
        if not bad and float(params.get("gauge_min", cls.PARAMS["gauge_min"])) > float(params.get("gauge_max", cls.PARAMS["gauge_max"])):
            bad.append(("gauge_min", "the first gauge lies beyond the last (gauge_max)"))
        if not bad and not 10.0 <= float(params.get("front_deg", cls.PARAMS["front_deg"])) <= 90.0:
            bad.append(("front_deg", f"{float(params['front_deg']):g}: the front face's angle to the slide's base, "
                                     "between 10 and 90 degrees (90: a box)"))
        need = ("thickness", "mass", "slope_deg")
        if not bad and all(params.get(k) is not None for k in need):
            S, M = float(params["thickness"]), float(params["mass"])
            D = float(params.get("density_ratio", cls.PARAMS["density_ratio"]))
            beta = math.radians(float(params.get("front_deg", cls.PARAMS["front_deg"])))
            if beta < 0.5 * math.pi and S / math.tan(beta) > _base_length(M / (D * S), S, beta):  # in units of h
                bad.append(("front_deg", f"{math.degrees(beta):g}: the front taper s/tan(front) = "
                                         f"{S / math.tan(beta):.3g} h is longer than the slide's base: raise M or the angle"))
        if not bad and all(params.get(k) is not None for k in need):
            # sliding with base friction = the driving force tips the block about its front edge unless the normal
            # force's shift (s/2) tan(alpha) stays within its half length: l/s >= tan(alpha), l = M h / (D S)
            S, M = float(params["thickness"]), float(params["mass"])
            D = float(params.get("density_ratio", cls.PARAMS["density_ratio"]))
            ratio, tan_a = M / (D * S * S), math.tan(math.radians(float(params["slope_deg"])))
            if ratio < tan_a:
                bad.append(("mass", f"the block (length/thickness M/(D S^2) = {ratio:.3g}) would topple on a "
                                    f"{float(params['slope_deg']):g} degree plane (it slides upright only for "
                                    f"length/thickness >= tan(alpha) = {tan_a:.3g}): raise M or lower S"))
        return bad

    @classmethod
    def scene(cls, params: dict) -> tuple[dict, dict]:
        p = {**cls.PARAMS, **params}
        h, F, S, M = float(p["depth_m"]), float(p["froude"]), float(p["thickness"]), float(p["mass"])
        a = math.radians(float(p["slope_deg"]))
        D = float(p["density_ratio"])
        rho_w = 1000.0
        dx = h / float(p["layers"])
        V = F * math.sqrt(G * h)
        s = S * h
        length = M * h / (D * S)  # M = D l s / h^2: the box's length (front_deg = 90)
        beta = math.radians(float(p["front_deg"]))
        base = _base_length(length, s, beta)  # the base of the trapezoid of the same area l s (= the box's l at 90)
        ca, sa = math.cos(a), math.sin(a)
        t = (ca, -sa)  # down the slope
        n = (sa, ca)  # the slope's outward normal
        x_toe = h / math.tan(a)
        # the plane: a right triangle whose hypotenuse is the slope line y = h - x tan(alpha), from the floor to
        # a margin above the block's start
        up = base + s + 4 * dx
        x_top, y_top = -up * ca, h + up * sa
        x_end = float(p["gauge_max"]) * h + 2.0 * h + base / F
        y_max = y_top + s + 4 * dx
        # the channel floor is a fixed block, not the tank's floor: a block landing on it pinches water against a
        # face the coupling knows, and its squeeze-out pushes that water along the gap (the tank, solid to blocks,
        # has no penalty faces: landing on it squeezed 2% of the water through it, docs/notes.md)
        floor_t = max(0.5 * h, 4 * dx)
        # block centroid: its lower front corner at the shoreline (0, h)
        cx = -0.5 * length * t[0] + 0.5 * s * n[0]
        cy = h - 0.5 * length * t[1] + 0.5 * s * n[1]
        c0 = float(p["sound_speed_factor"]) * max(V, math.sqrt(2.0 * G * h))
        mat = {"friction_angle_deg": float(p["slope_deg"]), "normal_stiffness_n_m": float(p["normal_stiffness_n_m"])}
        zd = 0.5 * Z_DEPTH
        duration = base / V + (float(p["gauge_max"]) + 3.0) * math.sqrt(h / G)
        xs = []
        X = float(p["gauge_min"])
        while X <= float(p["gauge_max"]) + 1e-9:
            xs.append(X)
            X += float(p["gauge_step"])
        slide = {"name": "slide", "density_kg_m3": D * rho_w, "velocity_m_s": [V * t[0], V * t[1], 0.0],
                 "material": dict(mat)}
        if beta >= 0.5 * math.pi - 1e-9:  # the box
            slide.update({"shape": "box", "size_m": [length, s, Z_DEPTH], "position_m": [cx, cy, 0.0],
                          "orientation_deg": [0.0, 0.0, -float(p["slope_deg"])]})
        else:  # a trapezoid: base from u = -base to 0 along the slope (u: down-slope, w: out of the slope), top
            # face from u = -base to -s/tan(front) at w = s; its front lower corner at the shoreline (0, h)
            taper = s / math.tan(beta)
            corners = [(-base, 0.0), (0.0, 0.0), (-taper, s), (-base, s)]
            slide.update({"shape": "prism", "vertices_m": [[u * t[0] + w * n[0], h + u * t[1] + w * n[1], z]
                                                            for u, w in corners for z in (-zd, zd)]})
        scene = {
            "simulation": {"dimension": 2, "duration_s": duration},
            "fluid": {"spacing_m": dx, "fidelity": p["fidelity"], "eos": {"type": "tait", "speed_of_sound_m_s": c0},
                      "regions": [{"box_min_m": [x_top, 0.0], "box_max_m": [x_end, h]}]},
            "tank": {"box_min_m": [x_top, -floor_t], "box_max_m": [x_end, y_max]},
            "blocks": [
                {"name": "floor", "shape": "box", "kind": "fixed", "material": dict(mat),
                 "size_m": [x_end - x_top, floor_t, Z_DEPTH], "position_m": [0.5 * (x_top + x_end), -0.5 * floor_t, 0.0]},
                {"name": "plane", "shape": "prism", "kind": "fixed", "material": dict(mat),
                 "vertices_m": [[x_toe, 0.0, -zd], [x_top, 0.0, -zd], [x_top, y_top, -zd],
                                [x_toe, 0.0, zd], [x_top, 0.0, zd], [x_top, y_top, zd]]},
                slide,
            ],
            "output": {"frame_rate_hz": 20.0},
            "hazard": {"sample_interval_s": 0.02 * math.sqrt(h / G),
                       "gauges": [{"name": f"x{X:g}", "position_m": [X * h, 0.0], "still_level_m": h} for X in xs],
                       "slides": [{"block": "slide"}]},
        }
        if p["block_walls"]:
            scene["coupling"] = {"block_walls": True}
        setup = {"h_m": h, "x0_m": 0.0, "F": F, "S": S, "M": M, "alpha_deg": float(p["slope_deg"]), "D": D,
                 "layers": float(p["layers"]), "spacing_m": dx, "slide_length_m": base, "front_deg": float(p["front_deg"]),
                 "slide_speed_m_s": V,
                 "slide_mass_kg_m": D * rho_w * length * s, "slide_area_m2": length * s, "rho_w": rho_w,
                 "channel_length_m": x_end}
        return scene, setup

    @staticmethod
    def compare(setup: dict, summary: dict) -> dict:
        row = compare_channel(setup, summary.get("hazard") or {}, summary.get("energy"))
        row["layers"] = setup["layers"]
        row["spacing_m"] = setup["spacing_m"]
        return row


def _base_length(length: float, s: float, beta: float) -> float:
    """The base of a trapezoidal slide of thickness s whose front face makes the angle beta with its base and whose
    area equals the box's l s: l s = base s - s^2 / (2 tan beta), so base = l + s / (2 tan beta) (= l at 90 deg)."""
    return length + (0.5 * s / math.tan(beta) if beta < 0.5 * math.pi - 1e-9 else 0.0)


GENERATORS = {ImpulseChannel2D.name: ImpulseChannel2D}
