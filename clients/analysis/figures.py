"""Pictures of an analysis (PNG, off-screen): sizes, sphericity, coordination, liquid fraction, growth law, T1 map.

Every picture is drawn from the analysis' own tables, on a bare matplotlib
Figure (:func:`bubsub.clients.pipeline.results.figures.subplots`), with units on its
axes; bubbles cut by the field of view are left out, as in the statistics.
A 4D analysis draws up to four subscans side by side in the histograms and
profiles, and adds the growth law and the T1 map.
"""

from __future__ import annotations

import numpy as np

from bubsub.core.io.atomic import atomic_path
from bubsub.clients.pipeline.results.figures import subplots

__all__ = ["write_figures", "FIGURES"]

#: File name -> what it shows.
FIGURES = {
    "sizes.png": "distribution of the equivalent diameters",
    "sphericity.png": "histogram of the sphericity",
    "coordination.png": "histogram of the coordination (contacts per bubble)",
    "liquid_fraction.png": "liquid fraction against the distance from the rotation axis and against height",
    "growth_law.png": "4D: d(V^(2/3))/dt against coordination, with the fitted law",
    "t1_map.png": "4D: positions of the T1 events, seen from above and from the side",
}


def _save(fig, path):
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")


def _number(v):
    return np.nan if v == "" or v is None else float(v)


def _whole(rows):
    return [r for r in rows if r.get("truncated") != 1]


def _groups(analysis, table):
    """``[(label, rows)]``: the whole table (3D) or up to four subscans spread over the series (4D)."""
    rows = analysis.tables[table]
    if analysis.kind == "3d":
        return [("", rows)]
    t_col = next(c for c in analysis.columns[table] if c.startswith("time_"))
    unit = t_col[len("time_"):]
    subs = sorted({r["subscan"] for r in rows})
    pick = [subs[int(round(i))] for i in np.linspace(0, len(subs) - 1, min(4, len(subs)))] if subs else []
    out = []
    for s in dict.fromkeys(pick):
        sel = [r for r in rows if r["subscan"] == s]
        out.append((f"t = {sel[0][t_col]:.3g} {unit}" if sel else f"subscan {s}", sel))
    return out


def _histograms(path, analysis, column, xlabel, title, integer=False, unit=""):
    fig, ax = subplots(figsize=(7, 4.5), dpi=100)
    groups = [(label, np.array([_number(r[column]) for r in _whole(rows)])) for label, rows in
              _groups(analysis, "bubbles")]
    groups = [(label, v[np.isfinite(v)]) for label, v in groups]
    every = np.concatenate([v for _, v in groups]) if groups else np.zeros(0)
    if every.size:
        if integer:
            bins = np.arange(every.min() - 0.5, every.max() + 1.5)
        else:
            spread = max(float(np.ptp(every)), 1e-6 * max(1.0, float(np.abs(every).max())))  # all equal: one bin
            mid = 0.5 * (every.min() + every.max())
            bins = np.histogram_bin_edges(every, bins=max(5, min(40, int(np.sqrt(every.size)) + 3)),
                                          range=(mid - 0.5 * spread, mid + 0.5 * spread))
        if len(groups) == 1:
            v = groups[0][1]
            ax.hist(v, bins=bins, color="tab:blue", edgecolor="white")
            ax.axvline(v.mean(), color="tab:orange", lw=1.5, label=f"mean {v.mean():.3g}{unit}")
        else:
            for label, v in groups:
                ax.hist(v, bins=bins, histtype="step", lw=1.3,
                        label=f"{label} (mean {v.mean():.3g}{unit})" if v.size else label)
        ax.legend(fontsize=8)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("bubbles (not cut by the field of view)")
    ax.yaxis.get_major_locator().set_params(integer=True)
    ax.set_title(f"{title}: {every.size} bubble{'s' if every.size != 1 else ''}"
                 + (" over the subscans shown" if len(groups) > 1 else ""), fontsize=10)
    _save(fig, path)


def _liquid_fraction(path, analysis):
    fig, (a, b) = subplots(1, 2, figsize=(11, 4.2), dpi=100)
    for label, rows in _groups(analysis, "shells"):
        r = [0.5 * (x["r_lo_mm"] + x["r_hi_mm"]) for x in rows]
        a.plot(r, [_number(x["liquid_fraction"]) for x in rows], marker="o", ms=4, label=label or None)
    a.set_xlabel("distance from the rotation axis (mm; shell centres)")
    a.set_ylabel("liquid fraction")
    a.set_title("cylindrical shells", fontsize=10)
    for label, rows in _groups(analysis, "grid"):
        layers = {}
        for x in rows:  # volume-weighted over each z layer of the grid
            key = (x["z_lo_mm"], x["z_hi_mm"])
            tot, gas = layers.get(key, (0.0, 0.0))
            layers[key] = (tot + x["region_volume_mm3"], gas + x["gas_volume_mm3"])
        keys = sorted(layers)
        z = [0.5 * (k[0] + k[1]) for k in keys]
        lf = [1 - layers[k][1] / layers[k][0] if layers[k][0] else np.nan for k in keys]
        b.plot(lf, z, marker="o", ms=4, label=label or None)
    b.set_xlabel("liquid fraction")
    b.set_ylabel("height z (mm; centres of the grid's layers)")
    b.set_title("layers of the Cartesian grid", fontsize=10)
    for ax in (a, b):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    _save(fig, path)


def _growth_law(path, analysis):
    rates = analysis.tables["rates"]
    rate_col = next(c for c in analysis.columns["rates"] if c.startswith("volume_two_thirds_rate"))
    unit = rate_col.split("_per_")[-1]
    z = np.array([r["coordination"] for r in rates if r[rate_col] != ""], dtype=float)
    y = np.array([r[rate_col] for r in rates if r[rate_col] != ""], dtype=float)
    fig, ax = subplots(figsize=(7, 4.5), dpi=100)
    ax.scatter(z, y, s=6, alpha=0.4, color="tab:blue", label="bubble, subscan")
    for v in np.unique(z):
        ax.plot(v, np.mean(y[z == v]), marker="s", color="tab:red", ms=5)
    law = analysis.summary.get("growth_law", {})
    if law.get("slope") is not None and len(z):
        xs = np.linspace(z.min(), z.max(), 2)
        ax.plot(xs, law["slope"] * xs + law["intercept"], color="black", lw=1.5,
                label=f"k = {law['slope']:.3g} +- {law['slope_stderr']:.2g} mm^2/{unit}, "
                      f"Z0 = {law['z0']:.3g} +- {law['z0_stderr']:.2g}")
    ax.axhline(0, color="grey", lw=0.6)
    ax.set_xlabel("coordination Z (contacts)")
    ax.set_ylabel(f"d(V^(2/3))/dt (mm^2/{unit})")
    ax.set_title(f"growth law d(V^(2/3))/dt = k (Z - Z0): {len(z)} rates (red: mean per Z)", fontsize=10)
    ax.legend(fontsize=8)
    _save(fig, path)


def _t1_map(path, analysis):
    rows = analysis.tables["t1"]
    t_col = next(c for c in analysis.columns["t1"] if c.endswith("_after"))
    fig, (a, b) = subplots(1, 2, figsize=(11, 4.6), dpi=100)
    pos = np.array([[r["x_mm"], r["y_mm"], r["z_mm"]] for r in rows], dtype=float).reshape(-1, 3)
    t = np.array([r[t_col] for r in rows], dtype=float)
    bub = analysis.tables["bubbles"]
    cen = np.array([[r["centroid_x_mm"], r["centroid_y_mm"], r["centroid_z_mm"]] for r in bub], dtype=float)
    for ax, (i, j), names in ((a, (0, 1), "xy"), (b, (0, 2), "xz")):
        ax.scatter(cen[:, i], cen[:, j], s=2, color="0.8", label="bubble centroids (all subscans)")
        if len(pos):
            shown = ax.scatter(pos[:, i], pos[:, j], c=t, s=30, cmap="viridis", edgecolors="black", linewidths=0.4)
        ax.set_xlabel(f"{names[0]} (mm)")
        ax.set_ylabel(f"{names[1]} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
    a.set_title(f"{len(pos)} T1 events, seen from above", fontsize=10)
    b.set_title("seen from the side", fontsize=10)
    if len(pos):
        fig.colorbar(shown, ax=[a, b], shrink=0.8).set_label(f"time after the swap ({t_col.split('_')[1]})")
    a.legend(fontsize=7, loc="upper right")
    _save(fig, path)


def write_figures(out, analysis):
    """Write the pictures of :data:`FIGURES` that apply (3D: the first four) into ``out``.

    Returns
    -------
    list of pathlib.Path
    """
    from pathlib import Path

    out = Path(out)
    _histograms(out / "sizes.png", analysis, "equivalent_diameter_mm",
                "equivalent diameter (mm; ball of equal volume)", "Bubble sizes", unit=" mm")
    _histograms(out / "sphericity.png", analysis, "sphericity", "sphericity pi^(1/3) (6V)^(2/3) / A", "Sphericity")
    _histograms(out / "coordination.png", analysis, "coordination",
                f"coordination (contacts closer than {analysis.summary['contact_gap_mm']:.3g} mm)", "Coordination",
                integer=True)
    _liquid_fraction(out / "liquid_fraction.png", analysis)
    names = ["sizes.png", "sphericity.png", "coordination.png", "liquid_fraction.png"]
    if analysis.kind == "4d":
        _growth_law(out / "growth_law.png", analysis)
        _t1_map(out / "t1_map.png", analysis)
        names += ["growth_law.png", "t1_map.png"]
    return [out / n for n in names]
