"""The edge profile of a real capture's Gray code stripes: how the camera sees a projector edge, against the
Gaussian blur the pattern model assumes.

From a capture with Gray code pairs (pattern and inverse) plus white and black frames (the procam_chessboard layout:
`../shared/data/procam_chessboard`), each lit pixel's projector row comes from the full decode (every bit, with
interpolation); its normalised intensity x = (I - black) / (white - black) in bit k's image is binned by the signed
distance (projector px) to that bit's nearest edge, positive on the pattern's white side. The median profile is
fitted with one Gaussian edge (lo + (hi - lo) Phi(d / sigma): the model's) and with a Gaussian core plus a wide halo
((1 - h) Phi(d / sigma) + h Phi(d / sigma_h)). x + x_inverse tells whether the camera is linear (a constant).

    python -m bench.edge_profile                                     # bits 2, 3, 5 and 6 of the row code, +-60 px
    python -m bench.edge_profile --bits 2 --range 60 --axis row --stem edge-profile-cpu

CPU, about a minute. Writes <out>/<stem>.json and .md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from bench import DATE, markdown_table, write_study
from slwarp.scans.data import data_dir

DEPTH_RANGE = (800.0, 2600.0)


def projector_coordinate(scan, axis: str, depth: np.ndarray | None = None) -> np.ndarray:
    """[H, W] projector row (axis 'row') or column of each pixel's point at `depth` (default: the full gc-interp
    decode); NaN without."""
    from slwarp.decode import reconstruct_depth
    from slwarp.neural.depth_maps import depth_to_points

    if depth is None:
        depth, _, _ = reconstruct_depth(scan, "gc-interp", depth_range=DEPTH_RANGE)
    ok = np.isfinite(depth)
    uv = np.asarray(scan.projector.project_camera_points(depth_to_points(depth, scan.camera).astype(np.float64)))
    out = np.full(depth.shape, np.nan)
    out[ok] = uv[:, 1 if axis == "row" else 0]
    return out


def edge_profile(scan, coord: np.ndarray, axis: str, bit: int, half_range: float, step: float) -> dict:
    """Bit `bit`'s median normalised intensity (and pattern + inverse) per signed distance bin to its nearest edge."""
    name = f"gc_{axis}_b{bit}"
    if name not in scan.names or name + "_inv" not in scan.names:
        raise SystemExit(f"{scan.source}: no frames {name} and {name}_inv")
    white, black = scan.images[scan.names.index("white")], scan.images[scan.names.index("black")]
    mod = white - black
    good = np.isfinite(coord) & (mod > 0.15)
    pattern = scan.patterns[scan.names.index(name)]
    line = pattern[:, 0] if axis == "row" else pattern[0, :]
    edges = np.where(np.diff(line) != 0)[0] + 0.5  # between projector pixels k and k + 1
    x = ((scan.images[scan.names.index(name)] - black) / np.maximum(mod, 1e-3))[good]
    xi = ((scan.images[scan.names.index(name + "_inv")] - black) / np.maximum(mod, 1e-3))[good]
    c = coord[good]
    k = np.clip(np.searchsorted(edges, c), 1, len(edges) - 1)
    nearest = np.where(np.abs(c - edges[k - 1]) < np.abs(c - edges[k]), edges[k - 1], edges[k])
    white_side = line[np.clip(np.round(c).astype(int), 0, len(line) - 1)] > 0.5
    d = np.abs(c - nearest) * np.where(white_side, 1.0, -1.0)
    bins = np.arange(-half_range, half_range + 1e-9, step)
    idx = np.digitize(d, bins)
    med, total = [], []
    for i in range(1, len(bins)):
        sel = idx == i
        med.append(float(np.median(x[sel])) if sel.sum() > 50 else float("nan"))
        total.append(float(np.median(x[sel] + xi[sel])) if sel.sum() > 50 else float("nan"))
    return {"bit": bit, "edge_spacing_px": float(np.diff(edges).min()), "d": (0.5 * (bins[1:] + bins[:-1])).tolist(),
            "x": med, "x_plus_inverse": total}


def fit_profiles(prof: dict) -> dict:
    """One Gaussian edge and a Gaussian core plus a halo, fitted to a profile (least squares)."""
    from scipy.optimize import curve_fit
    from scipy.special import erf

    d, x = np.asarray(prof["d"]), np.asarray(prof["x"])
    m = np.isfinite(x)
    phi = lambda t, s: 0.5 * (1 + erf(t / (s * np.sqrt(2))))  # noqa: E731
    one = lambda t, s, lo, hi: lo + (hi - lo) * phi(t, s)  # noqa: E731
    two = lambda t, s, h, sh, lo, hi: lo + (hi - lo) * ((1 - h) * phi(t, s) + h * phi(t, sh))  # noqa: E731
    p1, _ = curve_fit(one, d[m], x[m], p0=[0.7, 0.05, 0.95], maxfev=20000)
    p2, _ = curve_fit(two, d[m], x[m], p0=[0.7, 0.1, min(10.0, d.max() / 2), 0.02, 0.98], maxfev=20000,
                      bounds=([0.05, 0.0, 0.5, -0.5, 0.5], [10.0, 0.9, 10.0 * d.max(), 0.5, 1.5]))
    rms = lambda f, p: float(np.sqrt(np.mean((x[m] - f(d[m], *p)) ** 2)))  # noqa: E731
    return {"gaussian": {"sigma_px": p1[0], "lo": p1[1], "hi": p1[2], "rms": rms(one, p1)},
            "core_halo": {"sigma_px": p2[0], "halo_share": p2[1], "halo_sigma_px": p2[2], "lo": p2[3], "hi": p2[4],
                          "rms": rms(two, p2)}}


def fit_lens_tail(profiles: list[dict], scales: int = 2) -> dict:
    """One lens for every bit: a Gaussian core plus `scales` halos (share, sigma in projector px), shared by the
    profiles, each profile with its own lo / hi, fitted by least squares to their periodic stripes (each edge's
    neighbours at the bit's edge spacing, alternating). The real capture's profiles want two scales: each bit alone
    fits a halo of its own width (fit_profiles: 0.10 at 39 px for bit 2, 0.21 at 1.9 px for bit 6). Returns
    core_px, halos [(share, sigma_px), ...] (nearest first) and rms."""
    from scipy.optimize import least_squares
    from scipy.special import ndtr

    data = []
    for prof in profiles:
        d, x = np.asarray(prof["d"], np.float64), np.asarray(prof["x"], np.float64)
        m = np.isfinite(x)
        data.append((d[m], x[m], float(prof["edge_spacing_px"])))

    def stripes(d, sigma, spacing):  # the blurred pattern beside an edge at 0, white on the positive side
        k = np.arange(-8, 9)
        sign = (-1.0) ** k
        return (sign[:, None] * (ndtr((d[None, :] + k[:, None] * spacing) / sigma) - (k < 0)[:, None])).sum(0)

    def residuals(q):
        core, halo = q[0], q[1:1 + 2 * scales]
        out = []
        for i, (d, x, spacing) in enumerate(data):
            lo, hi = q[1 + 2 * scales + 2 * i:3 + 2 * scales + 2 * i]
            e = (1 - halo[0::2].sum()) * stripes(d, core, spacing)
            for j in range(scales):
                e = e + halo[2 * j] * stripes(d, halo[2 * j + 1], spacing)
            out.append(lo + (hi - lo) * e - x)
        return np.concatenate(out)

    start_sigmas = np.geomspace(3.0, 50.0, scales)
    q0 = [0.6] + [v for s in start_sigmas for v in (0.1, s)] + [0.03, 0.95] * len(data)
    lower = [0.1] + [0.0, 0.5] * scales + [-0.2, 0.5] * len(data)
    upper = [3.0] + [0.5, 300.0] * scales + [0.3, 1.3] * len(data)
    r = least_squares(residuals, q0, bounds=(lower, upper))
    halos = sorted((float(r.x[1 + 2 * j]), float(r.x[2 + 2 * j])) for j in range(scales))
    return {"core_px": float(r.x[0]), "halos": sorted(halos, key=lambda h: h[1]),
            "rms": float(np.sqrt(np.mean(r.fun ** 2)))}


def render(doc: dict) -> str:
    lines = [f"# The edge profile of a real capture's Gray code stripes (CPU, {doc['date']})", "",
             f"`{doc['command']}`", "",
             f"Capture: {doc['source']}. Normalised intensity x = (I - black) / (white - black) of bit k's image against the "
             "signed distance (projector px) to its nearest edge, positive on the white side, the projector coordinate "
             "from the full decode. Fits: one Gaussian edge (the pattern model's) and a Gaussian core plus a halo.", "",
             "## Fits", ""]
    rows = []
    for p in doc["profiles"]:
        g, h = p["fit"]["gaussian"], p["fit"]["core_halo"]
        rows.append([f"{p['bit']} (edges every {p['edge_spacing_px']:.0f} px)", f"{g['sigma_px']:.2f}",
                     f"{g['lo']:.3f} / {g['hi']:.3f}", f"{g['rms']:.4f}", f"{h['sigma_px']:.2f}",
                     f"{h['halo_share']:.3f}", f"{h['halo_sigma_px']:.1f}", f"{h['lo']:.3f} / {h['hi']:.3f}",
                     f"{h['rms']:.4f}", f"{np.nanmin(p['x_plus_inverse']):.3f}-{np.nanmax(p['x_plus_inverse']):.3f}"])
    lines += markdown_table(["bit", "Gaussian sigma px", "lo / hi", "rms", "core sigma px", "halo share",
                             "halo sigma px", "lo / hi", "rms", "x + inverse"], rows) + [""]
    lines += ["## Profiles (median x per distance bin)", ""]
    for p in doc["profiles"]:
        pick = [i for i, t in enumerate(p["d"]) if np.isfinite(p["x"][i])
                and (abs(t) <= 6 or abs(t) % 10 < 1 or abs(t) > max(p["d"]) - 1)]
        lines += [f"Bit {p['bit']}: " + ", ".join(f"{p['d'][i]:+.1f}: {p['x'][i]:.3f}" for i in pick), ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(data_dir() / "procam_chessboard"))
    ap.add_argument("--axis", choices=("row", "col"), default="row", help="the code whose stripes are measured")
    ap.add_argument("--bits", default="2,3,5,6")
    ap.add_argument("--range", type=float, default=60.0, help="half the distance range, projector px")
    ap.add_argument("--step", type=float, default=1.0, help="bin width, projector px")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--stem", default="edge-profile-cpu")
    args = ap.parse_args(argv)
    from slwarp.scans.scan import load_scan

    if not Path(args.data).is_dir():
        raise SystemExit(f"{args.data}: no capture there (--data FOLDER)")
    scan = load_scan(args.data)
    for need in ("white", "black"):
        if need not in scan.names:
            raise SystemExit(f"{args.data}: no '{need}' frame; the profile is normalised by white and black")
    coord = projector_coordinate(scan, args.axis)
    profiles = []
    for bit in (int(b) for b in args.bits.split(",")):
        prof = edge_profile(scan, coord, args.axis, bit, args.range, args.step)
        prof["fit"] = fit_profiles(prof)
        print(f"bit {bit}: Gaussian sigma {prof['fit']['gaussian']['sigma_px']:.2f} px; core "
              f"{prof['fit']['core_halo']['sigma_px']:.2f} px + halo {prof['fit']['core_halo']['halo_share']:.3f} at "
              f"{prof['fit']['core_halo']['halo_sigma_px']:.1f} px", flush=True)
        profiles.append(prof)
    doc = {"date": DATE, "command": "python -m bench.edge_profile " + " ".join(sys.argv[1:] if argv is None else argv),
           "source": str(scan.source), "axis": args.axis, "profiles": profiles}
    write_study(Path(args.out) / args.stem, doc, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
