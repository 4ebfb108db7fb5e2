"""How the single-shot composite pattern degrades: the statistics the thesis left open (7.2).

One factor at a time is swept away from the realistic capture of the accuracy benchmark
(smooth albedo 0.15-1.0, ambient 10 %, uncorrected projector gamma 2.2, 1 px blur in the
projector and the camera, shot + read noise, 8 bits), for the thesis's 4-bit pattern and
sliscan's default, on the sphere (every factor but slope) and on a tilted plane (slope):

* noise: the sensor's full well (shot noise) from noise-free to 150 electrons, reported as the
  measured carrier SNR (RMS of the carriers in a noise-free render over the RMS of the noise);
* ambient light: 0-50 % of the projector's full white;
* albedo contrast: a 40 mm checker whose dark squares reflect less and less (high 0.9);
* gamma mismatch: the pattern pre-corrected for a gamma that differs from the projector's 2.2
  (mismatch = projector gamma - pre-correction gamma; 2.2 = no pre-correction);
* blur: the projector's and the camera's Gaussian sigma (pixels);
* surface slope: a plane tilted about x (depth along the stripes' direction, stripes
  compressed) and about y (carriers compressed), 0-60 degrees.

For every point: stripe error rate (valid lit pixels decoded to a wrong stripe), completeness,
outliers and RMS 3D error (mm) against the simulator's ground truth, averaged over seeds.
Prints one table per factor, writes JSON and a PNG of the curves.

    python benchmarks/robustness.py --quick          # 1 seed, fewer levels (~15 min)
    python benchmarks/robustness.py --seeds 3 --plot docs/robustness.png --json benchmarks/robustness.json
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import uniform_filter1d

from sliscan import patterns, simulate
from sliscan.evaluate import accuracy
from sliscan.pipeline import Scanner
from sliscan.types import PatternSpec

BASE_GAMMA = 2.2


@dataclass(frozen=True)
class Factor:
    """One swept factor: its levels, and how a level changes the scene, conditions and pattern."""

    name: str
    unit: str
    levels: tuple[float, ...]
    quick_levels: tuple[float, ...]
    apply: Callable[[float, simulate.Conditions, PatternSpec], tuple[simulate.Surface, simulate.Conditions, PatternSpec]]


def base_conditions(seed: int) -> simulate.Conditions:
    """The accuracy benchmark's realistic capture (smooth albedo)."""
    return simulate.Conditions(albedo=simulate.SmoothAlbedo(low=0.15, high=1.0, seed=seed), ambient=0.1,
                               projector_gamma=BASE_GAMMA, projector_blur_px=1.0, camera_blur_px=1.0, seed=seed)


def _sphere(conditions: simulate.Conditions, spec: PatternSpec, **changes: object):
    return simulate.sphere_scene(), conditions.with_(**changes), spec


def _checker(low: float, conditions: simulate.Conditions, spec: PatternSpec):
    albedo = simulate.CheckerAlbedo(square_mm=40, low=low, high=0.9)
    return simulate.sphere_scene(), conditions.with_(albedo=albedo), spec


def _gamma_mismatch(mismatch: float, conditions: simulate.Conditions, spec: PatternSpec):
    precorrection = BASE_GAMMA - mismatch
    return simulate.sphere_scene(), conditions, spec.with_(gamma=1.0 if mismatch == BASE_GAMMA else precorrection)


def _tilt(axis: str) -> Callable:
    def apply(deg: float, conditions: simulate.Conditions, spec: PatternSpec):
        return simulate.tilted_plane_scene(deg, axis=axis), conditions, spec
    return apply


FACTORS = (
    Factor("noise", "full well (e-; 0 = noise-free)", (0, 40000, 10000, 2500, 600, 150), (0, 10000, 600, 150),
           lambda v, c, s: _sphere(c, s, full_well_e=None if v == 0 else v)),
    Factor("ambient", "fraction of full white", (0.0, 0.1, 0.2, 0.3, 0.5), (0.0, 0.2, 0.5),
           lambda v, c, s: _sphere(c, s, ambient=v)),
    Factor("albedo contrast", "dark square albedo (bright 0.9)", (0.9, 0.6, 0.4, 0.25, 0.1, 0.03), (0.9, 0.25, 0.05),
           _checker),
    Factor("gamma mismatch", "projector gamma - pre-correction gamma", (-0.6, -0.3, 0.0, 0.3, 0.6, BASE_GAMMA),
           (-0.3, 0.0, 0.3, BASE_GAMMA), _gamma_mismatch),
    Factor("blur", "sigma in projector and camera (px)", (0.0, 0.5, 1.0, 1.5, 2.0, 3.0), (0.0, 1.0, 2.0),
           lambda v, c, s: _sphere(c, s, projector_blur_px=v, camera_blur_px=v)),
    Factor("slope x", "tilt about x (deg)", (0, 15, 30, 45, 60), (0, 30, 60), _tilt("x")),
    Factor("slope y", "tilt about y (deg)", (0, 15, 30, 45, 60), (0, 30, 60), _tilt("y")),
)


def carrier_snr_db(clean: np.ndarray, noisy: np.ndarray, spec: PatternSpec, lit: np.ndarray) -> float:
    """Carrier SNR (dB) of a capture: carriers' RMS in the noise-free render over the noise's RMS.

    The carriers are the noise-free image minus its running mean over two periods of the
    lowest carrier along the carrier direction (rows orientation: along x).
    """
    axis = 1 if spec.orientation == "rows" else 0
    period = clean.shape[axis] / min(spec.carriers) * 2
    ac = clean - uniform_filter1d(clean, size=max(3, int(period)), axis=axis)
    noise = noisy.astype(np.float64) - clean
    return float(20 * np.log10(np.sqrt(np.mean(ac[lit] ** 2)) / max(np.sqrt(np.mean(noise[lit] ** 2)), 1e-12)))


def measure(rig: simulate.Rig, spec: PatternSpec, factor: Factor, level: float, seed: int) -> dict:
    """Scan one rendered capture at one level of one factor; accuracy figures and SNR."""
    scene, conditions, spec = factor.apply(level, base_conditions(seed), spec)
    image = patterns.render_pattern(spec)
    capture = simulate.render(rig, scene, image, conditions)
    t0 = time.perf_counter()
    result = Scanner(spec, rig.calibration).scan(capture.image)
    seconds = time.perf_counter() - t0
    acc = accuracy(result, capture.truth, spec, rig.calibration)
    row = dict(factor=factor.name, level=level, seed=seed, seconds=seconds, **acc.as_dict())
    if factor.name == "noise":
        clean = simulate.render(rig, scene, image, conditions.with_(full_well_e=None, bit_depth=None)).image
        row["snr_db"] = carrier_snr_db(clean, capture.image, spec, capture.truth.lit)
    return row


def averaged(rows: list[dict]) -> dict:
    """Mean of every numeric figure over seeds (NaN-aware for the error figures)."""
    out = {k: rows[0][k] for k in ("pattern", "factor", "level")}
    for key in ("completeness", "wrong_stripe", "outliers", "rms_mm", "median_mm", "snr_db"):
        values = [r[key] for r in rows if key in r]
        if values:
            finite = [v for v in values if np.isfinite(v)]
            out[key] = float(np.mean(finite)) if finite else float("nan")
    return out


def print_table(factor: Factor, levels: tuple[float, ...], rows: list[dict]) -> None:
    """One factor's table: a line per level, the figures of each pattern side by side."""
    names = sorted({r["pattern"] for r in rows})
    print(f"\n{factor.name} ({factor.unit})")
    head = f"{'level':>8s}" + ("" if factor.name != "noise" else f" {'SNR dB':>7s}")
    for n in names:
        head += f" | {n + ' wrong%':>19s} {'compl%':>7s} {'outl%':>6s} {'rms mm':>7s}"
    print(head)
    for level in levels:
        line_rows = {r["pattern"]: r for r in rows if r["level"] == level}
        line = f"{level:8g}"
        if factor.name == "noise":
            line += f" {np.mean([r['snr_db'] for r in line_rows.values()]):7.1f}"
        for n in names:
            r = line_rows[n]
            line += (f" | {100 * r['wrong_stripe']:19.2f} {100 * r['completeness']:7.1f} "
                     f"{100 * r['outliers']:6.2f} {r['rms_mm']:7.1f}")
        print(line, flush=True)


def plot(results: list[dict], path: Path) -> None:
    """Curves of stripe error rate and completeness per factor, one panel per factor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(FACTORS), figsize=(3.2 * len(FACTORS), 6), squeeze=False)
    for col, factor in enumerate(FACTORS):
        for name in sorted({r["pattern"] for r in results}):
            rows = [r for r in results if r["factor"] == factor.name and r["pattern"] == name]
            if not rows:
                continue
            x = [r.get("snr_db", r["level"]) if factor.name == "noise" else r["level"] for r in rows]
            axes[0, col].plot(x, [100 * r["wrong_stripe"] for r in rows], "o-", label=name)
            axes[1, col].plot(x, [100 * r["completeness"] for r in rows], "o-", label=name)
        axes[0, col].set_title(factor.name, fontsize=9)
        axes[1, col].set_xlabel("carrier SNR (dB)" if factor.name == "noise" else factor.unit, fontsize=7)
    axes[0, 0].set_ylabel("wrong stripe (% of valid)")
    axes[1, 0].set_ylabel("completeness (% of lit)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="1296x972")
    parser.add_argument("--projector", default="1024x768")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="1 seed and fewer levels")
    parser.add_argument("--factors", default=",".join(f.name for f in FACTORS))
    parser.add_argument("--json", default="benchmarks/robustness.json")
    parser.add_argument("--plot", default="docs/robustness.png")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    projector = tuple(int(v) for v in args.projector.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    specs = {"thesis 4-bit": patterns.thesis_spec(projector), "sliscan 4-bit": patterns.default_spec(projector)}
    seeds = range(1 if args.quick else args.seeds)
    chosen = [f for f in FACTORS if f.name in args.factors.split(",")]
    results = []
    for factor in chosen:
        levels = factor.quick_levels if args.quick else factor.levels
        rows = [averaged([dict(measure(rig, spec, factor, level, seed), pattern=name) for seed in seeds])
                for level in levels for name, spec in specs.items()]
        print_table(factor, levels, rows)
        results += rows
    Path(args.json).write_text(json.dumps({"camera": camera, "projector": projector, "seeds": len(seeds),
                                           "rows": results}, indent=1))
    plot(results, Path(args.plot))
    print(f"\nwrote {args.json} and {args.plot}")


if __name__ == "__main__":
    main()
