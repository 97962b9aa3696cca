#!/usr/bin/python3
"""Drawing half of `magvec report`: reads DIR/data/report.json and the CSVs next to it,
which the C++ side (host/report/report.cpp) computed, and writes DIR/*.png and DIR/index.html.
No number shown here is computed here, except formatting and axis limits.

Usage: magvec_report.py DIR
Exit codes: 0 ok, 2 bad input, 3 matplotlib missing, 4 numpy missing (read by render.cpp).
"""
import html
import json
import math
import os
import sys

try:
    import numpy as np
except ImportError:
    print("magvec_report.py: numpy is missing: apt-get install python3-numpy", file=sys.stderr)
    sys.exit(4)
try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
except ImportError:
    print("magvec_report.py: matplotlib is missing: apt-get install python3-matplotlib",
          file=sys.stderr)
    sys.exit(3)

DPI = 110
BEFORE = "#c0392b"
AFTER = "#1f5fa8"


def load_csv(path):
    a = np.genfromtxt(path, delimiter=",", names=True, comments="#", dtype=float)
    return np.atleast_1d(a)


def has_rows(a):
    return a is not None and a.size > 0


def equal_3d(ax, pts):
    lo = np.nanmin(pts, axis=0)
    hi = np.nanmax(pts, axis=0)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.nanmax(hi - lo)) * 1.05
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    try:
        ax.set_box_aspect((1, 1, 1))
    except AttributeError:
        pass


def fig_ellipsoid(rep, data, out):
    s = load_csv(os.path.join(data, "samples.csv"))
    surf = load_csv(os.path.join(data, "surface.csv"))
    n_lat, n_lon = rep["surface"]["n_lat"], rep["surface"]["n_lon"]
    f0 = rep["reference"]["F_nT"]

    def grid(prefix):
        return [surf[prefix + c + "_nT"].reshape(n_lat, n_lon) for c in "xyz"]

    fig = plt.figure(figsize=(11, 5.4))
    panels = [
        ("Raw samples m on the fitted ellipsoid", ["mx_nT", "my_nT", "mz_nT"], grid("e"),
         BEFORE, "m"),
        ("Calibrated h_s = W (m - o) on the sphere |h| = F", ["hsx_nT", "hsy_nT", "hsz_nT"],
         grid("s"), AFTER, "h_s"),
    ]
    for k, (title, cols, (gx, gy, gz), colour, sym) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.plot_wireframe(gx / 1e3, gy / 1e3, gz / 1e3, color="0.55", linewidth=0.4, alpha=0.6)
        pts = np.column_stack([s[c] for c in cols]) / 1e3
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=3, color=colour, alpha=0.7, depthshade=False)
        equal_3d(ax, np.vstack([pts, np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()]) / 1e3]))
        ax.set_title(title, fontsize=11)
        for setter, axis in ((ax.set_xlabel, "x"), (ax.set_ylabel, "y"), (ax.set_zlabel, "z")):
            setter(f"{sym}_{axis} [uT]", fontsize=9)
        ax.tick_params(labelsize=8)
        ax.view_init(elev=22, azim=-60)
    fig.suptitle(f"{s.size} of {rep['file_counts']['rows']} samples plotted; "
                 f"surface radius F = {f0:.1f} nT ({rep['reference']['source']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "fig_ellipsoid.png"), dpi=DPI)
    plt.close(fig)


def band_plot(ax, x, a, name, colour, label):
    ax.fill_between(x, a[name + "_min"], a[name + "_max"], color=colour, alpha=0.25, linewidth=0,
                    label="min..max per bucket")
    ax.plot(x, a[name + "_mean"], color=colour, linewidth=1.0, label=label)


def fig_residual(rep, data, out):
    r = load_csv(os.path.join(data, "residual.csv"))
    res = rep["residual"]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True)
    for ax, key, colour, title in ((axes[0], "before", BEFORE, "raw |m| - F"),
                                   (axes[1], "after", AFTER, "calibrated |h_s| - F")):
        st = res[key]
        band_plot(ax, r["t_s"], r, key, colour, "mean per bucket")
        ax.axhline(0, color="k", linewidth=0.6)
        ax.set_ylabel("|h| - F [nT]")
        ax.set_title(f"{title}: RMS {st['rms']:.3f} nT, mean {st['mean']:.3f} nT, "
                     f"n = {st['n']}", fontsize=11)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8, framealpha=0.8)
    axes[1].set_xlabel("t [s]")
    fig.suptitle(f"Total-field residual against the reference F "
                 f"({rep['file_counts']['bucket_rows']} rows per bucket)", fontsize=11)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "fig_residual.png"), dpi=DPI)
    plt.close(fig)


def fig_enu(rep, data, out):
    e = load_csv(os.path.join(data, "enu.csv"))
    comps = rep["enu"]["components"]
    fig, axes = plt.subplots(3, 2, figsize=(11, 7.5), sharex=True)
    for i, c in enumerate(comps):
        n = c["name"]
        for j, (key, colour, what) in enumerate((("before", BEFORE, "raw (R_bn^T m)"),
                                                 ("after", AFTER, "calibrated"))):
            ax = axes[i, j]
            band_plot(ax, e["t_s"], e, f"{n}_{key}", colour, "mean per bucket")
            if c["reference"] is not None:
                ax.axhline(c["reference"], color="k", linestyle="--", linewidth=0.8,
                           label="h_n of the calibration")
            st = c[key]
            ax.set_title(f"{n} {what}: mean {st['mean']:.1f}, SD {st['sd']:.2f} nT", fontsize=10)
            ax.set_ylabel(f"h_{n} [nT]")
            ax.grid(alpha=0.3)
            ax.ticklabel_format(axis="y", useOffset=False)
            if i == 0:
                ax.legend(loc="upper right", fontsize=7)
    axes[2, 0].set_xlabel("t [s]")
    axes[2, 1].set_xlabel("t [s]")
    fig.suptitle("East / North / Up components before and after calibration", fontsize=11)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "fig_enu.png"), dpi=DPI)
    plt.close(fig)


def fig_ekf(rep, data, out):
    t = load_csv(os.path.join(data, "trace.csv"))
    tr = rep["trace"]
    params = tr["params"]
    diags = tr.get("diagnostics", [])
    cols = t.dtype.names  # update, t_s, (state, sigma) per state, then the diagnostics
    panels = [(p["name"], cols[2 + 2 * k], cols[3 + 2 * k], p.get("truth"))
              for k, p in enumerate(params)]
    panels += [(d, cols[2 + 2 * len(params) + j], None, None) for j, d in enumerate(diags)]
    ncols = 3
    nrows = int(math.ceil(len(panels) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(11, 2.1 * nrows + 0.8), sharex=True,
                             squeeze=False)
    use_t = tr.get("x") == "t_s" and np.any(np.isfinite(t["t_s"]))
    x = t["t_s"] if use_t else t["update"]
    start = len(x) // 10  # axis limits from the last 90 %: the first sigmas are the prior's
    for k, (name, col, sigma_col, truth) in enumerate(panels):
        ax = axes[k // ncols, k % ncols]
        v = t[col]
        ax.plot(x, v, color=AFTER, linewidth=1.0)
        if sigma_col is not None:
            sg = t[sigma_col]
            if np.any(np.isfinite(sg)):
                ax.fill_between(x, v - sg, v + sg, color=AFTER, alpha=0.25, linewidth=0)
                lo = np.nanmin((v - sg)[start:])
                hi = np.nanmax((v + sg)[start:])
                if truth is not None:
                    lo, hi = min(lo, truth), max(hi, truth)
                if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
                    pad = 0.15 * (hi - lo)
                    ax.set_ylim(lo - pad, hi + pad)
            if truth is not None:
                ax.axhline(truth, color="k", linestyle="--", linewidth=0.8)
        elif name == "nis":
            ax.axhline(1.0, color="k", linestyle="--", linewidth=0.7)
        ax.set_title(name if sigma_col is not None else name + " (diagnostic)", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.grid(alpha=0.3)
    for k in range(len(panels), nrows * ncols):
        axes[k // ncols, k % ncols].set_visible(False)
    for j in range(ncols):
        axes[nrows - 1, j].set_xlabel("t [s]" if use_t else "update")
    title = (f"Filter states: estimate and 1-sigma band ({tr['updates']} trace rows)")
    if tr.get("truth_params"):
        title += "; dashed: the simulation's true value"
    fig.suptitle(title, fontsize=11)
    # Room for the title above the first row's panel titles.
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.45 / (2.1 * nrows + 0.8)))
    fig.savefig(os.path.join(out, "fig_ekf.png"), dpi=DPI)
    plt.close(fig)


def fig_coverage(rep, data, out):
    c = load_csv(os.path.join(data, "coverage.csv"))
    cov = rep["coverage"]
    nb, ns = cov["bands"], cov["sectors"]
    counts = c["count"].reshape(nb, ns)
    lat = np.radians(np.append(c["lat_lo_deg"].reshape(nb, ns)[:, 0],
                               c["lat_hi_deg"].reshape(nb, ns)[-1, 0]))
    lon = np.radians(np.append(c["lon_lo_deg"].reshape(nb, ns)[0, :],
                               c["lon_hi_deg"].reshape(nb, ns)[0, -1]))
    fig = plt.figure(figsize=(10, 6))
    ax = fig.add_subplot(1, 1, 1, projection="hammer")
    cmap = matplotlib.colormaps["viridis"].copy() if hasattr(matplotlib, "colormaps") \
        else plt.get_cmap("viridis").copy()
    cmap.set_bad("#dddddd")
    masked = np.ma.masked_where(counts <= 0, counts)
    vmax = max(float(counts.max()), 2.0)
    mesh = ax.pcolormesh(lon, lat, masked, cmap=cmap, norm=LogNorm(vmin=1, vmax=vmax),
                         edgecolors="white", linewidth=0.3, shading="flat")
    ax.grid(alpha=0.4)
    ax.tick_params(labelsize=8)
    cb = fig.colorbar(mesh, ax=ax, orientation="horizontal", fraction=0.05, pad=0.08)
    cb.set_label("samples per cell (grey: none)")
    ax.set_title(f"Coverage of the sphere of directions of h_s: {100 * cov['fraction']:.1f} % "
                 f"({cov['covered']} of {cov['cells']} equal-area cells)\n"
                 f"Hammer equal-area projection, longitude atan2(y, x), latitude asin(z)",
                 fontsize=11, pad=14)
    fig.savefig(os.path.join(out, "fig_coverage.png"), dpi=DPI)
    plt.close(fig)


DRAW = {
    "fig_ellipsoid.png": fig_ellipsoid,
    "fig_residual.png": fig_residual,
    "fig_enu.png": fig_enu,
    "fig_ekf.png": fig_ekf,
    "fig_coverage.png": fig_coverage,
}

CAPTIONS = {
    "fig_ellipsoid.png": "1. Raw samples on the fitted ellipsoid and calibrated samples on the "
                         "sphere",
    "fig_residual.png": "2. Total-field residual |h| - F before and after calibration",
    "fig_enu.png": "3. East/North/Up components before and after calibration",
    "fig_ekf.png": "4. Filter convergence: each state with its 1-sigma band (and the "
                   "simulation's true value, dashed, when the data file states it)",
    "fig_coverage.png": "5. Coverage of the sphere of directions (equal-area map)",
}


def e(x):
    return html.escape(str(x), quote=True)


def fmt(v, sigma=None):
    if v is None:
        return "&ndash;"
    if sigma is not None and sigma > 0 and math.isfinite(sigma):
        d = max(0, min(10, 1 - int(math.floor(math.log10(sigma)))))
        return f"{v:.{d}f}"
    return f"{v:.6g}"


def fmt_sigma(s):
    if s is None:
        return "&ndash;"
    return f"{s:.2g}"


CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;padding:0 12px;
color:#222;background:#fff;line-height:1.45}
main{max-width:1000px;margin:0 auto;padding-bottom:40px}
h1{font-size:1.5em;margin:18px 0 6px}h2{font-size:1.2em;margin:28px 0 8px;
border-bottom:1px solid #ddd;padding-bottom:3px}
img{max-width:100%;height:auto;display:block;border:1px solid #eee}
figure{margin:12px 0 24px}figcaption{font-size:.92em;color:#444;margin-top:4px}
.scroll{overflow-x:auto}
table{border-collapse:collapse;font-size:.92em;margin:6px 0}
th,td{padding:3px 8px;border-bottom:1px solid #e4e4e4;text-align:left;vertical-align:top}
td.n{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.g th{background:#f3f5f8}
.verdict{padding:10px 14px;border-radius:6px;margin:10px 0}
.ok{background:#e6f4ea;border:1px solid #9ccfa8}.bad{background:#fdecea;border:1px solid #e6a39b}
dl{display:grid;grid-template-columns:max-content 1fr;gap:2px 12px;margin:6px 0}
dt{font-weight:600}dd{margin:0;word-break:break-all}
.note{color:#555;font-size:.92em}
"""


def write_html(rep, out, figures):
    m, q = rep["meta"], rep["quality"]
    fc, cc = rep["file_counts"], rep["cal_counts"]
    res, cov = rep["residual"], rep["coverage"]
    p = []
    p.append("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
             "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
             f"<title>magvec calibration report: {e(os.path.basename(m['data_file']))}</title>\n"
             f"<style>{CSS}</style>\n</head>\n<body>\n<main>\n")
    p.append("<h1>magvec calibration report</h1>\n<dl>\n")
    for k, v in (("Data file", m["data_file"]), ("Calibration", m["cal_file"]),
                 ("Method", m["method"] or "(not stated in cal.json)"),
                 ("EKF trace", m["trace_file"] or "(none)"),
                 ("Calibrated by", f"magvec {m['cal_magvec_version']} at {m['cal_created_utc']}"
                                   f" from {m['cal_input']}"),
                 ("Report", f"magvec {m['magvec_version']}, created {m['created_utc']}")):
        p.append(f"<dt>{e(k)}</dt><dd>{e(v)}</dd>\n")
    p.append("</dl>\n")
    ok = q["verdict"] == "ok"
    p.append(f"<div class=\"verdict {'ok' if ok else 'bad'}\"><strong>Verdict: {e(q['verdict'])}"
             f"</strong><br>{e(q['reason'] or '(no reason given)')}</div>\n")

    p.append("<h2>Summary</h2>\n<div class=\"scroll\"><table>\n")
    rows = [
        ("Rows in the data file", fc["rows"]),
        ("Dropouts (non-finite samples)", fc["dropouts"]),
        ("Rows without a reference F", fc["without_reference"]),
        ("Rows without attitude", fc["without_attitude"]),
        (f"Outliers in the data file (|F - F_ref| > {fc['outlier_threshold_nT']:.3g} nT)",
         fc["outliers"]),
        ("Calibration: samples read", cc["samples"]),
        ("Calibration: samples used", cc["used"]),
        ("Calibration: skipped (non-finite)", cc["skipped_nonfinite"]),
        ("Calibration: rejected outliers", cc["rejected_outliers"]),
        ("Calibration: coverage figure", fmt(q["coverage"])),
        ("Calibration: condition number", fmt(q["condition"])),
        ("Calibration: residual RMS before / after [nT]",
         f"{fmt(q['residual_rms_before_nT'])} / {fmt(q['residual_rms_after_nT'])}"),
        ("This file: residual RMS before / after [nT]",
         f"{fmt(res['before']['rms'])} / {fmt(res['after']['rms'])}"),
        ("This file: coverage of directions",
         f"{100 * cov['fraction']:.1f} % ({cov['covered']} of {cov['cells']} cells)"),
    ]
    for k, v in rows:
        p.append(f"<tr><th>{e(k)}</th><td class=\"n\">{e(v) if not isinstance(v, str) else v}"
                 "</td></tr>\n")
    p.append("</table></div>\n")

    p.append("<h2>Figures</h2>\n")
    for f in figures:
        # The image links to itself: on a phone, a tap opens it full size.
        p.append(f"<figure><a href=\"{e(f)}\"><img src=\"{e(f)}\" alt=\"{e(CAPTIONS[f])}\"></a>"
                 f"<figcaption>{e(CAPTIONS[f])} (tap for full size)</figcaption></figure>\n")
    if "fig_enu.png" not in figures:
        p.append("<p class=\"note\">3. E/N/U components: the data file has no attitude.</p>\n")
    if "fig_ekf.png" not in figures:
        p.append("<p class=\"note\">4. Filter convergence: no trace given (--trace).</p>\n")
    if "fig_residual.png" not in figures:
        p.append("<p class=\"note\">2. Residual: the data file has no reference F "
                 "(F_nT column or --field-nT).</p>\n")

    p.append("<h2>6. Parameters (paper form, 1-sigma)</h2>\n<div class=\"scroll\"><table>\n"
             "<tr><th>parameter</th><th>value</th><th>1-sigma</th><th>unit</th></tr>\n")
    group = None
    for r in rep["table"]:
        if r["group"] != group:
            group = r["group"]
            p.append(f"<tr class=\"g\"><th colspan=\"4\">{e(group)}</th></tr>\n")
        p.append(f"<tr><td>{e(r['name'])}</td><td class=\"n\">{fmt(r['value'], r['sigma'])}</td>"
                 f"<td class=\"n\">{fmt_sigma(r['sigma'])}</td><td>{e(r['unit'])}</td></tr>\n")
    p.append("</table></div>\n<p class=\"note\">A scalar-only method (ellipsoid, EKF) determines "
             "W only up to a rotation; compare G = W<sup>T</sup>W, not C<sup>-1</sup> element by "
             "element. &ndash; means no 1-sigma in cal.json.</p>\n")
    if rep.get("trace"):
        truth = bool(rep["trace"].get("truth_params"))
        p.append("<h2>Filter: final estimates</h2>\n<div class=\"scroll\"><table>\n"
                 "<tr><th>state</th><th>value</th><th>1-sigma</th>"
                 + ("<th>truth</th><th>(value - truth) / 1-sigma</th>" if truth else "")
                 + "</tr>\n")
        for r in rep["trace"]["final"]:
            p.append(f"<tr><td>{e(r['name'])}</td><td class=\"n\">{fmt(r['value'], r['sigma'])}"
                     f"</td><td class=\"n\">{fmt_sigma(r['sigma'])}</td>")
            if truth:
                z = r.get("z")
                p.append(f"<td class=\"n\">{fmt(r.get('truth'), r['sigma'])}</td>"
                         f"<td class=\"n\">{'&ndash;' if z is None else f'{z:+.2f}'}</td>")
            p.append("</tr>\n")
        p.append("</table></div>\n")
        if truth:
            p.append("<p class=\"note\">Truth: the values the simulation states in the data "
                     "file's header, in the filter's parameterisation.</p>\n")
    p.append("</main>\n</body>\n</html>\n")
    tmp = os.path.join(out, "index.html.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write("".join(p))
    os.replace(tmp, os.path.join(out, "index.html"))


def main(argv):
    if len(argv) != 2:
        print("usage: magvec_report.py DIR", file=sys.stderr)
        return 2
    out = argv[1]
    data = os.path.join(out, "data")
    try:
        with open(os.path.join(data, "report.json"), encoding="utf-8") as f:
            rep = json.load(f)
    except (OSError, ValueError) as err:
        print(f"magvec_report.py: cannot read {data}/report.json: {err}", file=sys.stderr)
        return 2
    figures = rep["figures"]
    for name in figures:
        if name not in DRAW:
            print(f"magvec_report.py: unknown figure {name}", file=sys.stderr)
            return 2
        DRAW[name](rep, data, out)
    write_html(rep, out, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
