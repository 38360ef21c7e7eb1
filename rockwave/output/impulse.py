"""Landslide impulse waves: the laboratory predictors and a run's error against them.

The impulse product parameter (Heller & Hager 2010, J. Waterway Port Coastal Ocean Eng. 136(3) 145-155; the VAW
manual Heller, Hager & Minor 2009, VAW-Mitteilung 211, ETH Zurich, 2nd ed. Evers et al. 2019, VAW-Mitteilung 254,
Eq. 3.12)::

    P = F S^(1/2) M^(1/4) {cos[(6/7) alpha]}^(1/2)
    F = V_s / (g h)^(1/2)        slide Froude number (slide centroid velocity at impact)
    S = s / h                    relative slide thickness
    M = m_s / (rho_w b h^2)      relative slide mass (b: slide width = channel width; 2D: per unit width)

and the 2D (wave channel) relations of the maximum wave in the slide impact zone and its decay (manual Eqs. 3.13,
3.14, 3.16, 3.19; Heller & Hager 2010)::

    H_M / h = (5/9) P^(4/5)                      maximum wave height
    a_M / h = (4/9) P^(4/5)                      maximum crest amplitude (a = (4/5) H, Eq. 3.16)
    x_M / h = (11/2) P^(1/2)                     its distance from the impact point
    H(x) / h = (3/4) [P (x/h)^(-1/3)]^(4/5)      the decay along the channel, x > x_M
    a(x) / h = (3/5) [P (x/h)^(-1/3)]^(4/5)      (the same with a = (4/5) H)

Ranges of the data behind them (manual 2nd ed. Table 3-2): 0.86 <= F <= 6.83, 0.09 <= S <= 1.64, 0.11 <= M <= 10.02,
30 <= alpha <= 90 degrees, 0.17 <= P <= 8.13, 2.7 <= x/h <= 59.2. The manual's worked example (Lake Askja 2014,
2nd ed. Section 4.2.1: b = 550 m, s = 35.5 m, alpha = 10.4 deg, V_s = 30.1 m/s, m_s = 2e10 kg, h = 138 m) gives
P = 0.49, H_M = 43.3 m, x_M = 531 m; the 1st ed. Example 1 (V_s = 58 m/s, h = 80 m, s = 12 m, b = 100 m, 220,000 m^3
at 1700 kg/m^3, alpha = 40 deg) gives P = 0.64 (tests/test_impulse.py).

The error of a run is measured/predicted - 1 against ``band`` (default BAND = 0.3: +-30%); see docs/validation.md
("Landslide impulse waves") for what the band is and is not.
"""

from __future__ import annotations

import math

G = 9.81
BAND = 0.3  # the relative band the table marks 'within' (docs/validation.md: its source and status)

# ranges of the laboratory data behind the 2D relations (manual 2nd ed. Table 3-2)
RANGES = {"F": (0.86, 6.83), "S": (0.09, 1.64), "M": (0.11, 10.02), "alpha_deg": (30.0, 90.0), "P": (0.17, 8.13),
          "X": (2.7, 59.2)}


def impulse_product(F: float, S: float, M: float, alpha_deg: float) -> float:
    """P = F S^(1/2) M^(1/4) {cos[(6/7) alpha]}^(1/2) (Heller & Hager 2010; manual Eq. 3.12)."""
    c = math.cos(math.radians(6.0 / 7.0 * alpha_deg))
    return F * math.sqrt(S) * M ** 0.25 * math.sqrt(max(c, 0.0))


def slide_numbers(V_s: float, s: float, m_s: float, b: float, h: float, alpha_deg: float, rho_w: float = 1000.0,
                  g: float = G) -> dict:
    """F, S, M and P of a slide (SI units; 2D: m_s/b is the mass per unit width)."""
    F, S, M = V_s / math.sqrt(g * h), s / h, m_s / (rho_w * b * h * h)
    return {"F": F, "S": S, "M": M, "alpha_deg": alpha_deg, "P": impulse_product(F, S, M, alpha_deg)}


def max_wave_2d(P: float, h: float) -> dict:
    """The maximum wave in a channel: a_M = (4/9) P^(4/5) h, H_M = (5/9) P^(4/5) h, x_M = (11/2) P^(1/2) h."""
    return {"a_M_m": 4.0 / 9.0 * P ** 0.8 * h, "H_M_m": 5.0 / 9.0 * P ** 0.8 * h, "x_M_m": 5.5 * math.sqrt(P) * h}


def height_2d(P: float, x: float, h: float) -> float:
    """H(x) = (3/4) [P (x/h)^(-1/3)]^(4/5) h, for x > x_M (manual Eq. 3.19)."""
    return 0.75 * (P * (x / h) ** (-1.0 / 3.0)) ** 0.8 * h


def amplitude_2d(P: float, x: float, h: float) -> float:
    """a(x) = (4/5) H(x) = (3/5) [P (x/h)^(-1/3)]^(4/5) h, for x > x_M."""
    return 0.8 * height_2d(P, x, h)


def outside_ranges(nums: dict) -> list[str]:
    """The dimensionless numbers of a slide outside the ranges of the data behind the relations."""
    out = []
    for k, (lo, hi) in RANGES.items():
        v = nums.get(k)
        if v is not None and not lo <= v <= hi:
            out.append(f"{k}={v:.3g} not in [{lo:g}, {hi:g}]")
    return out


def _err(measured, predicted):
    if measured is None or predicted is None or not predicted or not math.isfinite(measured):
        return None
    return measured / predicted - 1.0


def compare_channel(setup: dict, hazard: dict, energy: dict | None = None, band: float = BAND) -> dict:
    """One scenario's wave against the 2D relations. ``setup``: h_m, x0_m (the impact point's x: the still shoreline),
    F, S, M, alpha_deg, and the slide's mass per unit width ``slide_mass_kg_m`` and volume ``slide_area_m2`` for the
    energy column; ``hazard``: the run's hazard summary (rockwave/output/hazard.py) with wave gauges named
    'x<X>' along the channel floor; those within the data's range of x/h (2.7 to 59.2) are compared. Returns flat columns: the predicted and measured a_M, H_M (= crest minus deepest
    trough at a gauge), x_M, their relative errors and whether they are within ``band``; the decay of H(x) and a(x)
    past the predicted x_M (mean and largest relative error); the slide's measured Froude number (its peak speed);
    and, with ``energy`` (run.json's energy summary), the fraction of the slide's kinetic energy in the water at the
    end (wave energy: the water's kinetic plus potential energy gained, less the potential energy of the water the
    resting slide displaces)."""
    h, x0 = float(setup["h_m"]), float(setup["x0_m"])
    nums = {k: float(setup[k]) for k in ("F", "S", "M", "alpha_deg")}
    P = impulse_product(nums["F"], nums["S"], nums["M"], nums["alpha_deg"])
    nums["P"] = P
    pred = max_wave_2d(P, h)
    row = {"P": P, "a_M_pred_m": pred["a_M_m"], "H_M_pred_m": pred["H_M_m"], "x_M_pred_m": pred["x_M_m"]}
    gauges = []
    for name, g in (hazard.get("gauges") or {}).items():
        if not name.startswith("x"):
            continue
        crest, trough = g.get("max_crest_m"), g.get("deepest_trough_m")
        if crest is None or trough is None:
            continue
        x = float(g["position_m"][0]) - x0
        if RANGES["X"][0] <= x / h <= RANGES["X"][1]:  # the relations hold where the laboratory measured them
            gauges.append((x, crest, crest - trough))
    gauges.sort()
    if gauges:
        ia = max(range(len(gauges)), key=lambda i: gauges[i][1])
        iH = max(range(len(gauges)), key=lambda i: gauges[i][2])
        row.update({"a_M_m": gauges[ia][1], "x_M_m": gauges[ia][0], "H_M_m": gauges[iH][2], "x_HM_m": gauges[iH][0],
                    "gauges_from_x_m": gauges[0][0], "gauges_to_x_m": gauges[-1][0]})
    else:
        row.update({"a_M_m": None, "x_M_m": None, "H_M_m": None, "x_HM_m": None})
    for k in ("a_M", "H_M", "x_M"):
        e = _err(row[f"{k}_m"], row[f"{k}_pred_m"])
        row[f"{k}_err"] = e
        if k != "x_M":
            row[f"{k}_within_band"] = None if e is None else abs(e) <= band
    far = [(x, a, H) for x, a, H in gauges if x > pred["x_M_m"]]
    eH = [H / height_2d(P, x, h) - 1.0 for x, _, H in far]
    ea = [a / amplitude_2d(P, x, h) - 1.0 for x, a, _ in far]
    row.update({"decay_gauges": len(far),
                "decay_H_mean_err": sum(eH) / len(eH) if eH else None,
                "decay_H_max_abs_err": max(map(abs, eH)) if eH else None,
                "decay_a_mean_err": sum(ea) / len(ea) if ea else None})
    slides = hazard.get("slides") or {}
    sl = next(iter(slides.values()), None)
    row["F_measured"] = sl["peak_speed_m_s"] / math.sqrt(G * h) if sl and sl.get("peak_speed_m_s") is not None else None
    row["outside_ranges"] = "; ".join(outside_ranges(nums))
    row["energy_to_water_fraction"] = None
    if energy and energy.get("start") and energy.get("end") and sl and setup.get("slide_mass_kg_m"):
        st, en = energy["start"], energy["end"]
        e_slide = 0.5 * float(setup["slide_mass_kg_m"]) * (nums["F"] * math.sqrt(G * h)) ** 2
        area = float(setup["slide_area_m2"])
        yc = float(sl["final_position_m"][1])
        # the resting slide (if under water) lifts its area of water onto the surface: rho_w g A (h + dh/2 - y_c)
        dh = area / float(setup["channel_length_m"])
        static = float(setup["rho_w"]) * G * area * max(h + 0.5 * dh - yc, 0.0) if yc < h else 0.0
        wave = en["water_kinetic_j"] + en["water_potential_j"] - st["water_potential_j"] - st["water_kinetic_j"] - static
        row["energy_to_water_fraction"] = wave / e_slide if e_slide > 0 else None
    return row


def summarise(rows: list[dict], by: str | None = None, band: float = BAND) -> list[dict]:
    """The mean signed error, mean |error| and the fraction within the band of a_M and H_M over the scenarios that
    ran, in groups of ``by`` (a column such as the resolution), in the order the groups first appear."""
    groups: dict = {}
    for r in rows:
        if r.get("status", "ok") != "ok" or r.get("a_M_err") is None:
            continue
        groups.setdefault(r.get(by) if by else "all", []).append(r)
    out = []
    for key, rs in groups.items():
        s = {"group": key, "scenarios": len(rs)}
        for k in ("a_M", "H_M", "x_M"):
            es = [r[f"{k}_err"] for r in rs if r.get(f"{k}_err") is not None]
            s[f"{k}_mean_err"] = sum(es) / len(es) if es else None
            s[f"{k}_mean_abs_err"] = sum(map(abs, es)) / len(es) if es else None
            if k != "x_M":
                s[f"{k}_within_band"] = sum(abs(e) <= band for e in es) / len(es) if es else None
        d = [r["decay_H_mean_err"] for r in rs if r.get("decay_H_mean_err") is not None]
        s["decay_H_mean_err"] = sum(d) / len(d) if d else None
        w = [r["wall_s"] for r in rs if r.get("wall_s") is not None]
        s["wall_s_mean"] = sum(w) / len(w) if w else None
        out.append(s)
    return out


def chart(rows: list[dict], profiles: dict, path, band: float = BAND, title: str = "") -> None:
    """comparison.png: (left) measured a_M/h and H_M/h against P with the relations (4/9) P^(4/5), (5/9) P^(4/5) and
    the band; (right) the height along the channel scaled by the relations, H(x)/(h P^(4/5)) against x/h, with
    (3/4) (x/h)^(-4/15) and the band. ``profiles``: scenario index -> [(x/h, H/h), ...] (crest minus trough at each
    gauge); ``rows``: the comparison rows (status, P, a_M_m, H_M_m, h_m, layers, index)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.get("status", "ok") == "ok" and r.get("a_M_m") is not None]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    if ok:
        ps = [float(r["P"]) for r in ok]
        lo, hi = min(ps) / 1.3, max(ps) * 1.3
        grid = [lo * (hi / lo) ** (k / 50) for k in range(51)]
        for coef, key, col, lab in ((4 / 9, "a_M_m", "C0", "a_M"), (5 / 9, "H_M_m", "C1", "H_M")):
            ax.plot(grid, [coef * p ** 0.8 for p in grid], "-", color=col, lw=1.2, label=f"{lab}/h = {coef * 9:.0f}/9 P^(4/5)")
            ax.fill_between(grid, [(1 - band) * coef * p ** 0.8 for p in grid], [(1 + band) * coef * p ** 0.8 for p in grid],
                            color=col, alpha=0.12)
            layers = sorted({r.get("layers") for r in ok}, key=lambda v: (v is None, v))
            for j, lay in enumerate(layers):
                sel = [r for r in ok if r.get("layers") == lay]
                ax.plot([float(r["P"]) for r in sel], [float(r[key]) / float(r["h_m"]) for r in sel], "os^Dv"[j % 5],
                        color=col, alpha=0.85, label=f"{lab} measured, h/dx = {lay:g}" if lay is not None else f"{lab} measured")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel("impulse product parameter P")
    ax.set_ylabel("a_M/h, H_M/h")
    ax.set_title(f"maximum wave (band ±{band:.0%})")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    xs = [x for prof in profiles.values() for x, _ in prof]
    if xs:
        grid = [min(xs) + (max(xs) - min(xs)) * k / 50 for k in range(51)]
        bx.plot(grid, [0.75 * x ** (-4 / 15) for x in grid], "k-", lw=1.4, label="H(x)/(h P^(4/5)) = (3/4) (x/h)^(-4/15)")
        bx.fill_between(grid, [(1 - band) * 0.75 * x ** (-4 / 15) for x in grid],
                        [(1 + band) * 0.75 * x ** (-4 / 15) for x in grid], color="k", alpha=0.1)
        byidx = {r["index"]: r for r in ok}
        for idx, prof in profiles.items():
            r = byidx.get(idx)
            if r is None or not prof:
                continue
            s = float(r["P"]) ** 0.8
            bx.plot([x for x, _ in prof], [H / s for _, H in prof], "-", lw=0.9, alpha=0.7,
                    label=f"#{idx} P={float(r['P']):.2f} h/dx={r.get('layers', 0):g}" if len(profiles) <= 12 else None)
        bx.axvline(RANGES["X"][0], color="grey", lw=0.8, ls=":")
    bx.set_xlabel("x/h (from the still shoreline)")
    bx.set_ylabel("H(x) / (h P^(4/5))")
    bx.set_title("decay along the channel")
    bx.grid(alpha=0.3)
    bx.legend(fontsize=6)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
