"""How single-shot and multi-shot scanning degrade: the statistics the thesis left open (7.2).

One factor at a time is swept away from the realistic capture of the accuracy benchmark
(smooth albedo 0.15-1.0, ambient 10 %, uncorrected projector gamma 2.2, 1 px blur in the
projector and the camera, shot + read noise, 8 bits) on the sphere (every factor but slope) and
on a tilted plane (slope), for four patterns (`--patterns`; specs from `methods.py`, as
`accuracy.py --compare`): the thesis's 4-bit composite pattern (`thesis`) and sliscan's default
(`sliscan`), one frame each; multi-frequency PMP, 1, 8 and 64 cycles x 4 steps (`pmp`, 12
frames); classic Gray code with 4-step phase refinement, 7 bits on 8-row codes (`graycode`,
20 frames: pattern/inverse pairs, white, black, fringes):

* noise: the sensor's full well (shot noise) from noise-free to 150 electrons, reported as the
  measured carrier SNR of the composite patterns (RMS of the carriers in a noise-free render
  over the RMS of the noise);
* ambient light: 0-50 % of the projector's full white;
* albedo contrast: a 40 mm checker whose dark squares reflect less and less (high 0.9);
* gamma mismatch: the pattern pre-corrected for a gamma that differs from the projector's 2.2
  (mismatch = projector gamma - pre-correction gamma; 2.2 = no pre-correction);
* blur: the projector's and the camera's Gaussian sigma (pixels);
* camera blur: the camera's alone, on the sphere under a 40 mm checker of 0.25 / 0.9 (an albedo
  edge is as sharp as the camera blurs it: the albedo-step detector measures it on the capture);
* projector focus and camera focus: a depth of field, the lens focused on the working point
  through an aperture of 0 (in focus at every depth: every other factor) to 16 mm
  (`simulate.Conditions.projector_focus_mm`): the sphere's front, 123 mm nearer, and the wall,
  200 mm farther, blurred more than its limbs (an 8 mm projector aperture: sigma 1.0 -> 1.3-1.5
  projector px);
* objects focus: the projector's depth of field again, on the `objects` scene (two spheres, a
  box and a lying cylinder 690-860 mm away before a wall at 1000 mm, which an aperture of 16 mm
  blurs by a disc of about 6 projector px: there sliscan's pattern loses its most significant
  bit where every stripe has it on);
* surface slope: a plane tilted about x (depth along the stripes' direction, stripes
  compressed) and about y (carriers compressed), 0-60 degrees;
* projector roll: the projector turned about its own optical axis, 0-10 degrees, as a rig's
  mounting leaves it (its field of view kept: the corners of the camera's view may go unlit),
  so that the stripes cross the camera's lines obliquely everywhere (the sphere);
* projector offset: the projector (200 mm above the camera) moved 0-100 mm sideways, still
  aimed at the working point (its field of view kept), so that depth moves the carriers (the
  sphere).

For every point and pattern: completeness (lit pixels with a point), outliers (valid points
farther from the truth than one stripe of the thesis's 4-bit pattern, or off any surface: one
yardstick for every pattern, as in `accuracy.py --compare`), gross outliers (the point's
projector row more than three such stripes from the true one), RMS and median 3D error (mm),
and for the composite patterns the stripe error rate (valid lit pixels decoded to a wrong
stripe; a multi-frame pattern has no stripes to be wrong about); means over seeds. A capture
the scanner refuses (an `InputError`, e.g. no carriers found) counts as completeness 0 and its
message is kept. All patterns of a point come from one render of the scene
(`methods.render_captures`: traced once, every frame with its own noise), and a point that
repeats another (the realistic capture is noise 10000 e-, gamma mismatch 2.2 and blur 1 px;
slope 0 about x and about y) is measured once. Prints one table per factor, writes JSON and a
PNG of the curves.

    python benchmarks/robustness.py --quick --seeds 2      # 960x720, fewer levels: ~30 min
    python benchmarks/robustness.py --seeds 3 --plot docs/robustness.png --json benchmarks/robustness.json
    python benchmarks/robustness.py --quick --patterns thesis,pmp --factors blur,"slope y"
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

from sliscan import InputError, patterns, simulate
from sliscan.evaluate import accuracy, gross_outliers, stripe_depth, surface_accuracy
from sliscan.pipeline import Scanner
from sliscan.types import MULTI_FRAME_KINDS, Calibration, PatternSpec, ScanResult

from methods import method_specs, render_captures

BASE_GAMMA = 2.2

#: `--patterns` keys -> names in `methods.method_specs`.
PATTERNS = {"thesis": "CP thesis 4-bit", "sliscan": "CP sliscan 4-bit", "pmp": "PMP 1,8,64 x 4",
            "graycode": "Gray code 7-bit + 4-step phase", "phase": "CP sliscan 4-bit + phase"}
#: Swept unless `--patterns` says otherwise (docs/accuracy.md's figure; "phase", issue 8's, is swept apart at 1296x972:
#: docs/accuracy.md, "The phase pattern under the same factors").
DEFAULT_PATTERNS = ("thesis", "sliscan", "pmp", "graycode")

#: The figures of a row, in table order (`wrong_stripe` only for the composite patterns).
FIGURES = ("completeness", "wrong_stripe", "outliers", "gross_outliers", "rms_mm", "median_mm")

Scene = tuple[simulate.Surface, simulate.Conditions]


def _same_pattern(level: float, spec: PatternSpec) -> PatternSpec:
    return spec


def _same_rig(level: float, rig: simulate.Rig) -> simulate.Rig:
    return rig


@dataclass(frozen=True)
class Factor:
    """One swept factor: its levels, and how a level changes the scene and conditions, the
    pattern, and the rig."""

    name: str
    unit: str
    levels: tuple[float, ...]
    quick_levels: tuple[float, ...]
    scene: Callable[[float, simulate.Conditions], Scene]
    pattern: Callable[[float, PatternSpec], PatternSpec] = _same_pattern
    rig: Callable[[float, simulate.Rig], simulate.Rig] = _same_rig


def base_conditions(seed: int) -> simulate.Conditions:
    """The accuracy benchmark's realistic capture (smooth albedo)."""
    return simulate.Conditions(albedo=simulate.SmoothAlbedo(low=0.15, high=1.0, seed=seed), ambient=0.1,
                               projector_gamma=BASE_GAMMA, projector_blur_px=1.0, camera_blur_px=1.0, seed=seed)


def _sphere(conditions: simulate.Conditions, **changes: object) -> Scene:
    return simulate.sphere_scene(), conditions.with_(**changes)


def _checker(low: float, conditions: simulate.Conditions) -> Scene:
    return _sphere(conditions, albedo=simulate.CheckerAlbedo(square_mm=40, low=low, high=0.9))


#: Where the depth-of-field factors focus each lens: the working point, 800 mm along the
#: camera's axis and ``hypot(800, 200)`` mm along the projector's (it sits 200 mm above).
FOCUS_MM = {"camera": 800.0, "projector": float(np.hypot(800.0, 200.0))}


def _focused(device: str, surface: Callable[[], simulate.Surface] = simulate.sphere_scene,
             ) -> Callable[[float, simulate.Conditions], Scene]:
    """A factor's scene: `surface` (the sphere), `device` ("camera" or "projector") focused on
    the working point through an aperture of the level (mm; 0: in focus at every depth)."""
    def scene(aperture: float, conditions: simulate.Conditions) -> Scene:
        if aperture == 0:
            return surface(), conditions
        lens = {f"{device}_focus_mm": FOCUS_MM[device], f"{device}_aperture_mm": aperture}
        return surface(), conditions.with_(**lens)
    return scene


def _precorrected(mismatch: float, spec: PatternSpec) -> PatternSpec:
    return spec.with_(gamma=1.0 if mismatch == BASE_GAMMA else BASE_GAMMA - mismatch)


def _moved(argument: str) -> Callable[[float, simulate.Rig], simulate.Rig]:
    """A factor's rig: `rig` (a `simulate.virtual_rig`) with the `virtual_rig` `argument` at
    the level, its projector's field of view kept."""
    def rig_at(level: float, rig: simulate.Rig) -> simulate.Rig:
        if level == 0:
            return rig
        projector = rig.calibration.projector
        fov = float(np.degrees(2 * np.arctan(projector.size[0] / 2 / rig.projector.K[0, 0])))
        return simulate.virtual_rig(camera_size=rig.calibration.camera.size, projector_size=projector.size,
                                    projector_fov_deg=fov, **{argument: level})
    return rig_at


def _tilt(axis: str) -> Callable[[float, simulate.Conditions], Scene]:
    def scene(deg: float, conditions: simulate.Conditions) -> Scene:
        return simulate.tilted_plane_scene(deg, axis=axis), conditions
    return scene


FACTORS = (
    Factor("noise", "full well (e-; 0 = noise-free)", (0, 40000, 10000, 2500, 600, 150), (0, 10000, 600, 150),
           lambda v, c: _sphere(c, full_well_e=None if v == 0 else v)),
    Factor("ambient", "fraction of full white", (0.0, 0.1, 0.2, 0.3, 0.5), (0.0, 0.2, 0.5),
           lambda v, c: _sphere(c, ambient=v)),
    Factor("albedo contrast", "dark square albedo (bright 0.9)", (0.9, 0.6, 0.4, 0.25, 0.1, 0.03), (0.9, 0.4, 0.25, 0.05),
           _checker),
    Factor("gamma mismatch", "projector gamma - pre-correction gamma", (-0.6, -0.3, 0.0, 0.3, 0.6, BASE_GAMMA),
           (-0.3, 0.0, 0.3, BASE_GAMMA), lambda v, c: _sphere(c), _precorrected),
    Factor("blur", "sigma in projector and camera (px)", (0.0, 0.5, 1.0, 1.5, 2.0, 3.0), (0.0, 1.0, 2.0),
           lambda v, c: _sphere(c, projector_blur_px=v, camera_blur_px=v)),
    Factor("camera blur", "camera sigma (px), 40 mm checker of 0.25 / 0.9", (0.5, 1.0, 1.5, 2.0, 2.5),
           (0.5, 1.0, 2.0), lambda v, c: _checker(0.25, c.with_(camera_blur_px=v))),
    Factor("projector focus", "projector aperture (mm; 0 = all in focus)", (0, 4, 8, 12, 16), (0, 8, 16),
           _focused("projector")),
    Factor("camera focus", "camera aperture (mm; 0 = all in focus)", (0, 3, 6, 9, 12), (0, 6, 12), _focused("camera")),
    Factor("objects focus", "projector aperture (mm), objects before a wall", (0, 4, 8, 12, 16), (0, 8, 16),
           _focused("projector", simulate.objects_scene)),
    Factor("slope x", "tilt about x (deg)", (0, 15, 30, 45, 60), (0, 30, 60), _tilt("x")),
    Factor("slope y", "tilt about y (deg)", (0, 15, 30, 45, 60), (0, 30, 60), _tilt("y")),
    Factor("projector roll", "turn about its axis (deg)", (0, 1, 2, 3, 5, 10), (0, 3, 10),
           lambda v, c: _sphere(c), rig=_moved("projector_roll_deg")),
    Factor("projector offset", "sideways, 200 mm above (mm)", (0, 25, 50, 65, 80, 100), (0, 50, 100),
           lambda v, c: _sphere(c), rig=_moved("projector_offset_mm")),
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


def score(result: ScanResult, truth: simulate.GroundTruth, spec: PatternSpec, calibration: Calibration,
          yardstick: PatternSpec, depth: NDArray[np.float32]) -> dict[str, float]:
    """The figures of one scan (`FIGURES`).

    A composite pattern is scored by `accuracy`, on its own stripes (the thesis's 16 stripes of
    48 rows; sliscan's 15 of 51.2 rows); a multi-frame one by `surface_accuracy` and
    `gross_outliers` on `yardstick`'s stripes (`depth` = its `stripe_depth`).
    """
    if spec.kind not in MULTI_FRAME_KINDS:
        figures = accuracy(result, truth, spec, calibration).as_dict()
    else:
        figures = surface_accuracy(result, truth, depth).as_dict()
        figures["gross_outliers"] = gross_outliers(result, truth, yardstick, calibration)
    if not result.valid.any():  # shares of no valid points: undefined, not 0
        figures.update({key: float("nan") for key in ("wrong_stripe", "outliers", "gross_outliers") if key in figures})
    return {key: figures[key] for key in FIGURES if key in figures}


class Sweep:
    """Measures points of the sweeps for a set of patterns, each distinct point once.

    Parameters
    ----------
    rig : Rig
        The rig of every factor but those that change it (`Factor.rig`).
    specs : dict
        Pattern name -> spec (before a factor changes it).
    """

    def __init__(self, rig: simulate.Rig, specs: dict[str, PatternSpec]) -> None:
        self.rig = rig
        self.specs = specs
        self.yardstick = patterns.thesis_spec(rig.calibration.projector.size)
        self._measured: dict[tuple, tuple[list[dict], bool]] = {}
        self._clean: dict[tuple, list[NDArray[np.float32]]] = {}

    def point(self, factor: Factor, level: float, seed: int) -> list[dict]:
        """One row per pattern for `factor` at `level` and seed `seed`; with the composite
        patterns' carrier SNR (`snr_db`) on the noise factor."""
        scene, conditions = factor.scene(level, base_conditions(seed))
        specs = {name: factor.pattern(level, spec) for name, spec in self.specs.items()}
        rig = factor.rig(level, self.rig)
        with_snr = factor.name == "noise"
        key = (rig.calibration.projector.matrix.tobytes(), scene, conditions, tuple(specs.values()))
        if key not in self._measured or (with_snr and not self._measured[key][1]):
            self._measured[key] = (self._measure(rig, scene, conditions, specs, with_snr), with_snr)
        rows = [dict(row) for row in self._measured[key][0]]
        for row in rows:
            if not with_snr:
                row.pop("snr_db", None)
            row.update(factor=factor.name, level=level, seed=seed)
        return rows

    def _measure(self, rig: simulate.Rig, scene: simulate.Surface, conditions: simulate.Conditions,
                 specs: dict[str, PatternSpec], with_snr: bool) -> list[dict]:
        calibration = rig.calibration
        frames, truth = render_captures(rig, scene, list(specs.values()), conditions)
        depth = stripe_depth(truth, self.yardstick, calibration)
        rows = []  # one per pattern, in the order of `specs`
        for (name, spec), capture in zip(specs.items(), frames):
            t0 = time.perf_counter()
            try:
                result = Scanner(spec, calibration).scan(capture)
            except InputError as error:
                rows.append(dict(pattern=name, seconds=time.perf_counter() - t0, completeness=0.0, error=str(error)))
                continue
            seconds = time.perf_counter() - t0
            rows.append(dict(pattern=name, seconds=seconds, **score(result, truth, spec, calibration,
                                                                    self.yardstick, depth)))
        if with_snr:
            single = [k for k, spec in enumerate(specs.values()) if spec.kind not in MULTI_FRAME_KINDS]
            spec_list = list(specs.values())
            clean = self._clean_frames(scene, conditions, [spec_list[k] for k in single])  # noise: base rig
            for k, clean_frame in zip(single, clean):
                rows[k]["snr_db"] = carrier_snr_db(clean_frame, frames[k], spec_list[k], truth.lit)
        return rows

    def _clean_frames(self, scene: simulate.Surface, conditions: simulate.Conditions,
                      specs: list[PatternSpec]) -> list[NDArray[np.float32]]:
        """Noise-free float renders of composite patterns (the same for every noise level)."""
        clean = conditions.with_(full_well_e=None, bit_depth=None)
        key = (scene, clean, tuple(specs))
        if key not in self._clean:
            self._clean[key] = render_captures(self.rig, scene, specs, clean)[0] if specs else []
        return self._clean[key]


def averaged(rows: list[dict]) -> dict:
    """Mean of every figure over seeds (of the seeds that have it, NaN-aware); refused captures
    as a count and their distinct messages."""
    out = {k: rows[0][k] for k in ("pattern", "factor", "level")}
    for key in (*FIGURES, "snr_db", "seconds"):
        values = [r[key] for r in rows if key in r]
        if values:
            finite = [v for v in values if np.isfinite(v)]
            out[key] = float(np.mean(finite)) if finite else float("nan")
    errors = [r["error"] for r in rows if "error" in r]
    if errors:
        out["errors"] = f"{len(errors)}/{len(rows)} seeds"
        out["error"] = "; ".join(dict.fromkeys(errors))
    return out


def _cell(row: dict, key: str, scale: float, fmt: str) -> str:
    value = row.get(key, float("nan"))
    return format("-", ">" + fmt.split(".")[0]) if not np.isfinite(value) else format(scale * value, fmt)


def print_table(factor: Factor, levels: tuple[float, ...], rows: list[dict]) -> None:
    """One factor's table: a line per level and pattern."""
    print(f"\n{factor.name} ({factor.unit})")
    names = list(dict.fromkeys(r["pattern"] for r in rows))
    print(f"{'level':>8s}  {'pattern':32s} {'SNR dB':>6s} {'compl%':>6s} {'wrong%':>6s} {'outl%':>6s} "
          f"{'gross%':>6s} {'rms mm':>7s} {'med mm':>6s}")
    for level in levels:
        for name in names:
            r = next(r for r in rows if r["level"] == level and r["pattern"] == name)
            note = f"  refused ({r['errors']}): {r['error']}" if "error" in r else ""
            print(f"{level:8g}  {name:32s} {_cell(r, 'snr_db', 1, '6.1f')} {_cell(r, 'completeness', 100, '6.1f')} "
                  f"{_cell(r, 'wrong_stripe', 100, '6.2f')} {_cell(r, 'outliers', 100, '6.2f')} "
                  f"{_cell(r, 'gross_outliers', 100, '6.3f')} {_cell(r, 'rms_mm', 1, '7.1f')} "
                  f"{_cell(r, 'median_mm', 1, '6.1f')}{note}", flush=True)


def markdown_table(results: list[dict]) -> str:
    """All rows as one Markdown table: a line per factor level, a column per pattern, each cell
    completeness / outliers / gross outliers (%), and the stripe error rate of a composite
    pattern in brackets."""
    names = list(dict.fromkeys(r["pattern"] for r in results))
    lines = ["| factor | level | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for factor in FACTORS:
        levels = list(dict.fromkeys(r["level"] for r in results if r["factor"] == factor.name))
        for i, level in enumerate(levels):
            cells = []
            for name in names:
                r = next(r for r in results if r["factor"] == factor.name and r["level"] == level
                         and r["pattern"] == name)
                cell = (f"{_cell(r, 'completeness', 100, '.1f')} / {_cell(r, 'outliers', 100, '.2f')} / "
                        f"{_cell(r, 'gross_outliers', 100, '.2f')}")
                if np.isfinite(r.get("wrong_stripe", float("nan"))):
                    cell += f" ({_cell(r, 'wrong_stripe', 100, '.1f')})"
                cells.append(cell + (" refused" if "error" in r else ""))
            snr = [r["snr_db"] for r in results if r["factor"] == factor.name and r["level"] == level and "snr_db" in r]
            label = f"{level:g}" + (f" ({np.mean(snr):.0f} dB)" if snr else "")
            lines.append(f"| {factor.name if i == 0 else ''} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path) -> None:
    """Completeness (top) and outliers (bottom, solid; the composite patterns' wrong stripes
    dotted) against the level of each factor, one column per factor, a colour per pattern."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    factors = [f for f in FACTORS if any(r["factor"] == f.name for r in results)]
    names = list(dict.fromkeys(r["pattern"] for r in results))
    colours = dict(zip(names, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    fig, axes = plt.subplots(2, len(factors), figsize=(2.9 * len(factors), 6.6), squeeze=False)
    for col, factor in enumerate(factors):
        rows = [r for r in results if r["factor"] == factor.name]
        snr = {r["level"]: r["snr_db"] for r in rows if "snr_db" in r}
        use_snr = factor.name == "noise" and all(r["level"] in snr for r in rows)
        for name in names:
            mine = [r for r in rows if r["pattern"] == name]
            x = [snr[r["level"]] if use_snr else r["level"] for r in mine]
            percent = {key: [100 * r.get(key, float("nan")) for r in mine] for key in FIGURES}
            axes[0, col].plot(x, percent["completeness"], "o-", color=colours[name])
            axes[1, col].plot(x, percent["outliers"], "o-", color=colours[name])
            if any("wrong_stripe" in r for r in mine):
                axes[1, col].plot(x, percent["wrong_stripe"], "s:", color=colours[name])
        axes[0, col].set_title(factor.name, fontsize=9)
        axes[1, col].set_xlabel("carrier SNR (dB)" if use_snr else factor.unit, fontsize=7)
    axes[0, 0].set_ylabel("completeness (% of lit pixels)")
    axes[1, 0].set_ylabel("% of valid points")
    handles = [Line2D([], [], color=colours[n], marker="o", label=n) for n in names] + [
        Line2D([], [], color="grey", marker="o", label="outliers (> 1 stripe off)"),
        Line2D([], [], color="grey", marker="s", linestyle=":", label="wrong stripe (composite patterns)")]
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", help="WxH (default 1296x972; 960x720 with --quick)")
    parser.add_argument("--projector", default="1024x768")
    parser.add_argument("--seeds", type=int, help="seeds per point (default 2; 1 with --quick)")
    parser.add_argument("--quick", action="store_true",
                        help="fewer levels, a 960x720 camera unless --camera, 1 seed unless --seeds")
    parser.add_argument("--patterns", default=",".join(DEFAULT_PATTERNS), help=f"comma-separated, of {', '.join(PATTERNS)}")
    parser.add_argument("--factors", default=",".join(f.name for f in FACTORS))
    parser.add_argument("--json", default="benchmarks/robustness.json")
    parser.add_argument("--plot", default="docs/robustness.png")
    parser.add_argument("--markdown", help="also write the table of docs/accuracy.md (one line per level) to this file")
    args = parser.parse_args()
    chosen_patterns = args.patterns.split(",")
    chosen = [f for f in FACTORS if f.name in args.factors.split(",")]
    unknown = (set(chosen_patterns) - set(PATTERNS)) | (set(args.factors.split(",")) - {f.name for f in FACTORS})
    if unknown:
        parser.error(f"unknown pattern or factor {', '.join(sorted(unknown))}")
    camera = tuple(int(v) for v in (args.camera or ("960x720" if args.quick else "1296x972")).split("x"))
    projector = tuple(int(v) for v in args.projector.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    everything = method_specs(projector)
    sweep = Sweep(rig, {PATTERNS[key]: everything[PATTERNS[key]] for key in chosen_patterns})
    seeds = range(args.seeds or (1 if args.quick else 2))
    results = []
    for factor in chosen:
        levels = factor.quick_levels if args.quick else factor.levels
        t0 = time.perf_counter()
        measured = []
        for level in levels:
            for seed in seeds:
                measured += sweep.point(factor, level, seed)
                print(f"  {factor.name} {level:g} seed {seed}: {time.perf_counter() - t0:.0f} s", file=sys.stderr,
                      flush=True)
        rows = [averaged([r for r in measured if r["level"] == level and r["pattern"] == name])
                for level in levels for name in sweep.specs]
        print_table(factor, levels, rows)
        results += rows
    Path(args.json).write_text(json.dumps({"camera": camera, "projector": projector, "seeds": len(seeds),
                                           "patterns": list(sweep.specs), "rows": results}, indent=1))
    plot(results, Path(args.plot))
    if args.markdown:
        Path(args.markdown).write_text(markdown_table(results))
    print(f"\nwrote {args.json} and {args.plot}")


if __name__ == "__main__":
    main()
