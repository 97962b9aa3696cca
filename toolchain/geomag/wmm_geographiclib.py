#!/usr/bin/env python3
"""WMM coefficients for magvec's reference field (host/geomag), reproducibly.

NOAA NCEI's WMM2025COF.zip (WMM.COF, WMM2025_TestValues.txt) is the authoritative source, but
it is not reachable from the build machines; the npm packages below carry the same public-domain
numbers. This script rebuilds the two NOAA text files from them, cross-checks two independent
copies of the coefficients, and converts WMM.COF to GeographicLib's MagneticModel format (a text
metadata file NAME.wmm plus the binary NAME.wmm.cof).

  # npm pack geomagnetism@0.2.0 magvar@2.2.0; tar xf each into geomagnetism/ and magvar/
  wmm_geographiclib.py cof-from-npm geomagnetism/package/data/wmm-2025.json \
      magvar/package/src/WMMCOF2025.js > data/geomag/WMM2025.COF
  wmm_geographiclib.py testvalues-from-npm geomagnetism/package/test/values.csv \
      > data/geomag/WMM2025_TestValues.txt
  wmm_geographiclib.py convert data/geomag/WMM2025.COF data/geomag/wmm2025

With a genuine NOAA WMM.COF, only the last step is needed.
"""
import datetime
import json
import re
import struct
import sys

NMAX = 12


def die(msg):
    sys.exit("wmm_geographiclib.py: " + msg)


def tenths(x):
    """Coefficients are published to 0.1 nT (nT/yr): compare and print them as integer tenths."""
    return int(round(float(x) * 10))


def read_geomagnetism_json(path):
    d = json.load(open(path))
    if d.get("name") != "WMM-2025" or d.get("epoch") != 2025 or d.get("n_max") != NMAX:
        die(path + ": not the WMM-2025 degree-12 model")
    rows = {}
    for n in range(1, NMAX + 1):
        for m in range(n + 1):
            i = n * (n + 1) // 2 + m  # the package's triangular index (cof.js)
            rows[(n, m)] = tuple(
                tenths(d[k][i])
                for k in ("main_field_coeff_g", "main_field_coeff_h", "secular_var_coeff_g",
                          "secular_var_coeff_h"))
    return rows


def read_magvar_js(path):
    text = open(path).read()
    tables = {}
    for name in ("gnmWmm", "hnmWmm", "gtnmWmm", "htnmWmm"):
        m = re.search(name + r"\s*=\s*\[(.*?)\];", text, re.S)
        if not m:
            die(path + ": no " + name)
        tables[name] = [[float(v) for v in re.findall(r"-?\d+(?:\.\d+)?", row)]
                        for row in re.findall(r"\[([^\[\]]*)\]", m.group(1))]
    rows = {}
    for n in range(1, NMAX + 1):
        for m in range(n + 1):
            rows[(n, m)] = tuple(tenths(tables[k][n][m])
                                 for k in ("gnmWmm", "hnmWmm", "gtnmWmm", "htnmWmm"))
    return rows


def fmt(t):
    return "%.1f" % (t / 10.0)


def cof_from_npm(json_path, js_path):
    a = read_geomagnetism_json(json_path)
    b = read_magvar_js(js_path)
    diff = [k for k in a if a[k] != b[k]]
    if diff:
        die("the two copies differ at (n, m) " + ", ".join("%d %d" % k for k in diff))
    # NOAA's WMM.COF layout: header (epoch, name, release date), n m g h gdot hdot, two 9-lines.
    out = ["    2025.0            WMM-2025     11/13/2024"]
    for n in range(1, NMAX + 1):
        for m in range(n + 1):
            g, h, gd, hd = a[(n, m)]
            out.append("%3d%3d%10s%10s%11s%11s" % (n, m, fmt(g), fmt(h), fmt(gd), fmt(hd)))
    out += ["9" * 48, "9" * 48]
    sys.stdout.write("\n".join(out) + "\n")


def testvalues_from_npm(csv_path):
    """geomagnetism's test/values.csv holds NOAA's 100 WMM2025 test values (its 2025.0-2029.5
    rows) reordered as date,alt,lat,lon,x,y,z,h,f,incl,decl,gv; write them back in the order of
    NOAA's WMM2025_TestValues.txt: date, height (km), lat, lon, D, I, H, X, Y, Z, F (nT, deg)."""
    lines = open(csv_path).read().split("\n")
    head = lines[0].split(",")
    col = {k: head.index(k) for k in head}
    print("# WMM2025 test values (NOAA NCEI / BGS, with WMM2025COF.zip), 100 points.")
    print("# Date HAE_km Lat_deg Lon_deg D_deg I_deg H_nT X_nT Y_nT Z_nT F_nT")
    count = 0
    for line in lines[1:]:
        v = line.split(",")
        if len(v) != len(head) or float(v[col["date"]]) < 2025.0:
            continue
        print(" ".join(v[col[k]] for k in ("date", "alt", "lat", "lon", "decl", "incl", "h", "x",
                                           "y", "z", "f")))
        count += 1
    if count != 100:
        die("expected 100 WMM2025 rows, found %d" % count)


def read_cof(path):
    lines = [l.split() for l in open(path) if l.strip()]
    epoch, name, release = float(lines[0][0]), lines[0][1], lines[0][2]
    coef = {}
    for f in lines[1:]:
        if f[0].startswith("9999"):
            break
        n, m = int(f[0]), int(f[1])
        coef[(n, m)] = tuple(float(x) for x in f[2:6])
    nmax = max(n for n, _ in coef)
    for n in range(1, nmax + 1):
        for m in range(n + 1):
            if (n, m) not in coef:
                die("%s: no coefficient n=%d m=%d" % (path, n, m))
    return epoch, name, release, nmax, coef


def pack_harmonic(nmax, value):
    """GeographicLib's SphericalEngine::coeff layout: int32 N, int32 M, then the cosine (g)
    coefficients with m outermost (m = 0..M, n = m..N), then the sine (h) ones for m >= 1,
    little-endian doubles. n = 0 is a zero term (a magnetic model has no monopole)."""
    cos, sin = [], []
    for m in range(nmax + 1):
        for n in range(m, nmax + 1):
            g, h = value(n, m) if n > 0 else (0.0, 0.0)
            cos.append(g)
            if m > 0:
                sin.append(h)
    return struct.pack("<ii", nmax, nmax) + struct.pack("<%dd" % len(cos), *cos) + struct.pack(
        "<%dd" % len(sin), *sin)


def convert(cof_path, out_base):
    epoch, name, release, nmax, coef = read_cof(cof_path)
    if name != "WMM-2025":
        die(cof_path + ": this conversion states WMM2025's validity and release; got " + name)
    ident = "WMM2025A"  # GeographicLib's 8-character ID, checked against the binary's header
    rel = datetime.datetime.strptime(release, "%m/%d/%Y").date().isoformat()
    meta = f"""WMMF-2
# World Magnetic Model 2025 (NOAA NCEI / British Geological Survey), public domain.
# Converted by magvec's toolchain/geomag/wmm_geographiclib.py from {cof_path.split('/')[-1]}.
Name            wmm2025
Description     World Magnetic Model 2025
URL             https://www.ncei.noaa.gov/products/world-magnetic-model
Publisher       National Oceanic and Atmospheric Administration
ReleaseDate     {rel}
ConversionDate  2026-11-25
DataVersion     1
Radius          6371200
NumModels       1
Epoch           {epoch:g}
DeltaEpoch      5
MinTime         {epoch:g}
MaxTime         {epoch + 5:g}
MinHeight       -1000
MaxHeight       850000
Normalization   Schmidt
ByteOrder       Little
ID              {ident}
"""
    with open(out_base + ".wmm", "w") as f:
        f.write(meta)
    with open(out_base + ".wmm.cof", "wb") as f:
        f.write(ident.encode("ascii"))
        f.write(pack_harmonic(nmax, lambda n, m: coef[(n, m)][0:2]))  # main field at the epoch
        f.write(pack_harmonic(nmax, lambda n, m: coef[(n, m)][2:4]))  # secular variation /yr


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "cof-from-npm":
        cof_from_npm(sys.argv[2], sys.argv[3])
    elif len(sys.argv) == 3 and sys.argv[1] == "testvalues-from-npm":
        testvalues_from_npm(sys.argv[2])
    elif len(sys.argv) == 4 and sys.argv[1] == "convert":
        convert(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
