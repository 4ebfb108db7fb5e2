"""Accuracy of single-shot composite-pattern scanning on the virtual rig.

For every pattern (the thesis's 4-bit pattern, sliscan's default, 6 and 8 bits), decoder
(sliscan's window demodulator; the thesis's Butterworth band-pass) and scene (sphere, steps,
tilted plane) under realistic conditions (smooth albedo 0.15-1.0 or a sharp checker 0.25/0.9,
ambient 10 %, uncorrected projector gamma 2.2, projector and camera blur 1 px, shot and read
noise, 8 bits), render a capture, scan it and compare with the ground truth
(`sliscan.evaluate`).  Prints a table and writes it as JSON.

    python benchmarks/accuracy.py                       # thesis sizes: 2592x1944 camera
    python benchmarks/accuracy.py --camera 1296x972 --seeds 1 --quick
    python benchmarks/accuracy.py --patterns "sliscan 6-bit,sliscan 8-bit" --scenes sphere
    python benchmarks/accuracy.py --quick --captures /tmp/captures   # render once, rescan later
    python benchmarks/accuracy.py --compare --camera 1296x972        # single shot vs multi-shot
    python benchmarks/accuracy.py --methods window --scenes cylinder,objects   # shapes not tuned on

`--compare` prints instead the comparison the thesis made (its figs. 3.28 and 6.2), made
quantitative: the thesis's 4-bit composite pattern, sliscan's, classic multi-shot Gray code
(OpenCV's sequence, one code per projector row: 10 bits for 768 rows; and with 4-step phase
refinement on 8-row codes), and multi-frequency PMP (frequencies 1, 8, 64 x 4 steps), on the
sphere and the steps under clean conditions (noise-free, linear projector, no blur, no
ambient, uniform albedo) and realistic ones (as above, smooth albedo): RMS, median and 95th
percentile 3D error, completeness, outliers (farther than one stripe of the 4-bit pattern
from the truth: one yardstick for all), the radius fitted to the sphere (122.555 mm), frames.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from sliscan import patterns, simulate
from sliscan.evaluate import accuracy, sphere_fit, stripe_depth, surface_accuracy
from sliscan.pipeline import Scanner

from methods import method_specs, render_captures, truth_arrays, truth_from

SCENES = {
    "sphere": simulate.sphere_scene,
    "steps": simulate.steps_scene,
    "tilted": simulate.tilted_plane_scene,
    "cylinder": simulate.cylinder_scene,
    "objects": simulate.objects_scene,
}
#: The scenes of the README's table; the others (`--scenes cylinder,objects`) check that its
#: figures hold on shapes the decoder was not tuned on (docs/accuracy.md, "Other scenes").
TABLE_SCENES = ("sphere", "steps", "tilted")


def pattern_specs(projector: tuple[int, int], quick: bool) -> dict[str, patterns.PatternSpec]:
    """The patterns compared: the thesis's, sliscan's default, and the same with more bits.

    More bits use carriers spread evenly up to the thesis's highest (an 8-pixel period in
    the projector, which the default rig's camera resolves with 2.5 pixels per projector
    pixel), so the window grows with the number of bits.
    """
    width = projector[0]
    specs = {"thesis 4-bit": patterns.thesis_spec(projector), "sliscan 4-bit": patterns.default_spec(projector),
             "sliscan 4-bit + phase": patterns.phase_spec(projector)}
    if not quick:
        # the variants below were measured on the phase pattern before its drive was stretched
        # (twenty-eighth session): each carrier an equal share of [0, 1], spanning 0.25-0.89
        base = patterns.phase_spec(projector, a_p=0.5, b_p=0.5 / 7)
        specs["4-bit + phase (equal-share drive)"] = base
        # issue 8's variant that lost: the phase channel on the lowest carriers, the bits above
        specs["4-bit + phase on low carriers"] = base.with_(carriers=tuple(sorted(base.phase_carriers + (base.carriers[0],), reverse=True)),
                                                            phase_carriers=tuple(sorted(base.carriers)[:3]))
        # more of the drive on the phase carriers: each bit weaker (b_p keeps the drive in range)
        for weight in (1.5, 2.0):
            specs[f"4-bit + phase (phase weight {weight:g})"] = base.with_(
                phase_weight=weight, b_p=0.5 / (base.bits + len(base.phase_carriers) * weight))
        # a finer fringe (1.5 stripes instead of 2): lower noise in projector lines, but a Gray
        # code off by one stripe deep inside a stripe no longer unwraps to the right period
        specs["4-bit + phase (period 1.5 stripes)"] = base.with_(phase_period=1.5 * base.phase_lines / base.stripes)
        # wider carrier spacing (seventeenth session): a shorter window, so less light from across
        # an edge in it, but higher carriers, which the blur of both devices weakens
        for spacing in (40, 48, 64):
            specs[f"sliscan 4-bit (spacing {spacing})"] = patterns.default_spec(
                projector, carriers=patterns.scale_carriers(tuple(spacing * k for k in (4, 3, 2, 1)), width))
        # the thesis's bit order (most significant bit on the lowest carrier, least on the
        # highest: an unclear least significant bit costs at most one stripe, and the highest
        # carrier is the one a projector's blur weakens most; fifty-first session, docs/design.md,
        # "The bit order")
        for name in ("sliscan 4-bit", "sliscan 4-bit + phase"):
            specs[f"{name} (thesis bit order)"] = specs[name].with_(carriers=tuple(sorted(specs[name].carriers)))
        for bits in (6, 8):
            carriers = tuple(k * width / 8 / bits for k in range(1, bits + 1))
            specs[f"thesis-style {bits}-bit"] = patterns.PatternSpec(
                projector_size=projector, bits=bits, carriers=carriers, weights=(1.0,) * bits, a_p=0.5, b_p=0.5 / bits)
            specs[f"sliscan {bits}-bit"] = patterns.default_spec(projector, bits=bits)
        specs.update({name: specs[source] for name, (source, _) in DECODER_VARIANTS.items()})
    return specs


#: Decoder variants (Scanner keyword arguments) of a pattern, each a row of the table on that
#: pattern's captures: what the default decoder's parts are worth.
DECODER_VARIANTS = {
    "sliscan 4-bit (per-pixel decisions)": ("sliscan 4-bit", dict(decode_options=dict(order=False))),
    "sliscan 4-bit + phase (per-pixel decisions)": ("sliscan 4-bit + phase", dict(decode_options=dict(order=False))),
    "sliscan 4-bit + phase (no smoothing)": ("sliscan 4-bit + phase", dict(fringe_options=dict(smooth=False))),
    "sliscan 4-bit + phase (no rescue)": ("sliscan 4-bit + phase", dict(fringe_options=dict(rescue=False))),
    "sliscan 4-bit + phase (no extension)": ("sliscan 4-bit + phase", dict(fringe_options=dict(extend=False))),
    "sliscan 4-bit + phase (extension unlimited)": ("sliscan 4-bit + phase",
                                                    dict(fringe_options=dict(extend_reach=0))),
    "sliscan 4-bit + phase (no unmixing)": ("sliscan 4-bit + phase", dict(fringe_options=dict(unmix=False))),
    "sliscan 4-bit + phase (levels from single pixels)": ("sliscan 4-bit + phase",
                                                          dict(fringe_options=dict(average_levels=False))),
    "sliscan 4-bit + phase (no recentring)": ("sliscan 4-bit + phase", dict(fringe_options=dict(recentre_phase=False))),
    "sliscan 4-bit + phase (DC-weighted phasors)": ("sliscan 4-bit + phase",
                                                    dict(fringe_options=dict(dc_weights=True))),
    "sliscan 4-bit + phase (boxes stop at gaps)": ("sliscan 4-bit + phase", dict(fringe_options=dict(bridge=False))),
    "sliscan 4-bit + phase (no recentring along the phase)": ("sliscan 4-bit + phase",
                                                              dict(fringe_options=dict(recentre_rows=False))),
    "sliscan 4-bit + phase (no edge margin)": ("sliscan 4-bit + phase", dict(fringe_options=dict(edge_margin=False))),
    "sliscan 4-bit + phase (no contrast test near jumps)": ("sliscan 4-bit + phase",
                                                            dict(fringe_options=dict(near_jump_contrast=float("inf")))),
    "sliscan 4-bit + phase (no shadow-side test)": ("sliscan 4-bit + phase",
                                                    dict(fringe_options=dict(shadow_sides=False))),
    "sliscan 4-bit + phase (no short-run test)": ("sliscan 4-bit + phase", dict(fringe_options=dict(short_run=0))),
    "sliscan 4-bit + phase (no mid-run test)": ("sliscan 4-bit + phase",
                                                dict(fringe_options=dict(mid_run_contrast=float("inf")))),
    "sliscan 4-bit + phase (no gap ring)": ("sliscan 4-bit + phase", dict(fringe_options=dict(gap_ring=0))),
    "4-bit + phase (equal-share drive, no gap ring)": ("4-bit + phase (equal-share drive)",
                                                       dict(fringe_options=dict(gap_ring=0))),
    "sliscan 4-bit + phase (one-period windows only)": ("sliscan 4-bit + phase",
                                                         dict(fringe_options=dict(ramped_windows=False))),
    "sliscan 4-bit + phase (no one-sided ramps)": ("sliscan 4-bit + phase",
                                                   dict(fringe_options=dict(one_sided_windows=False))),
    "sliscan 4-bit + phase (frame's ends clipped)": ("sliscan 4-bit + phase",
                                                     dict(fringe_options=dict(frame_ends=False))),
    "sliscan 4-bit + phase (strict Gray code)": ("sliscan 4-bit + phase",
                                                 dict(decode_options=dict(order=False, min_snr=3.0, min_confidence=0.1))),
    "thesis 4-bit (per-pixel decisions)": ("thesis 4-bit", dict(decode_options=dict(order=False))),
    "thesis 4-bit (stripe centres)": ("thesis 4-bit", dict(interpolate_stripes=False)),
    "sliscan 4-bit (stripe centres)": ("sliscan 4-bit", dict(interpolate_stripes=False)),
    "sliscan 4-bit + phase (no border lines)": ("sliscan 4-bit + phase", dict(interpolate_stripes=False)),
    "thesis 4-bit (chosen windows' borders)": ("thesis 4-bit", dict(centred_borders=False)),
    "sliscan 4-bit (chosen windows' borders)": ("sliscan 4-bit", dict(centred_borders=False)),
    "sliscan 4-bit + phase (chosen windows' borders)": ("sliscan 4-bit + phase", dict(centred_borders=False)),
    "thesis 4-bit (no typical slope)": ("thesis 4-bit", dict(typical_slope=False)),
    "sliscan 4-bit (no typical slope)": ("sliscan 4-bit", dict(typical_slope=False)),
    "thesis 4-bit (no lines beside)": ("thesis 4-bit", dict(lines_beside=False)),
    "sliscan 4-bit (no lines beside)": ("sliscan 4-bit", dict(lines_beside=False)),
    # the albedo steps all sharp (`Scanner.albedo` "sharp-steps"), as until the forty-fifth
    # session: the flat ones are blurred by default for the stripe patterns (docs/accuracy.md,
    # "Soft albedo edges")
    "thesis 4-bit (sharp albedo steps)": ("thesis 4-bit", dict(albedo="sharp-steps")),
    "sliscan 4-bit (sharp albedo steps)": ("sliscan 4-bit", dict(albedo="sharp-steps")),
    # not decoders but the edge trim (`Scanner.trim_edges`), a trade of points for RMS; 10 px
    # is meant for the 5 MP camera (about a ninth of its window): docs/accuracy.md
    "thesis 4-bit (edges trimmed 10 px)": ("thesis 4-bit", dict(trim_edges=10)),
    "sliscan 4-bit (edges trimmed 10 px)": ("sliscan 4-bit", dict(trim_edges=10)),
    "sliscan 4-bit + phase (edges trimmed 10 px)": ("sliscan 4-bit + phase", dict(trim_edges=10)),
}


def conditions(albedo: str, seed: int) -> simulate.Conditions:
    """Realistic capture conditions of issue 2 with a smooth or a checker albedo."""
    texture = (simulate.SmoothAlbedo(low=0.15, high=1.0, seed=seed) if albedo == "smooth"
               else simulate.CheckerAlbedo(square_mm=40, low=0.25, high=0.9))
    return simulate.Conditions(albedo=texture, ambient=0.1, projector_gamma=2.2, projector_blur_px=1.0,
                               camera_blur_px=1.0, seed=seed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="2592x1944")
    parser.add_argument("--projector", default="1024x768")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--quick", action="store_true", help="only the 4-bit patterns")
    parser.add_argument("--patterns", default="", help="comma-separated pattern names to keep (default: all)")
    parser.add_argument("--scenes", default=",".join(TABLE_SCENES), help=f"comma-separated, of {', '.join(SCENES)}")
    parser.add_argument("--albedo", default="smooth,checker")
    parser.add_argument("--methods", default="window,bandpass",
                        help="comma-separated Scanner methods: window, bandpass, baseband (stripe patterns only)")
    parser.add_argument("--json", default="benchmarks/accuracy.json")
    parser.add_argument("--markdown", help="also write the table as Markdown (as in the README) to this file")
    parser.add_argument("--compare", action="store_true", help="single shot vs multi-shot (see above)")
    parser.add_argument("--captures", help="folder caching the rendered captures and truths (npz), so a re-run "
                        "(e.g. before and after a change to the decoder) scans the same frames without rendering")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    projector = tuple(int(v) for v in args.projector.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    if args.compare:
        compare(rig, projector, args)
        return
    rows = []
    header = (f"{'pattern':22s} {'decoder':9s} {'scene':7s} {'albedo':8s} {'seed':>4s} {'stripe%':>8s} {'off>1%':>6s} "
              f"{'complete%':>9s} {'outlier%':>8s} {'gross%':>6s} {'rms mm':>8s} {'med mm':>7s} {'oracle med':>10s} {'s':>5s}")
    print(header)
    keep = [p for p in args.patterns.split(",") if p]
    for name, spec in pattern_specs(projector, args.quick).items():
        if keep and name not in keep:
            continue
        image = patterns.render_pattern(spec)
        for scene_name in args.scenes.split(","):
            scene = SCENES[scene_name]()
            for albedo in args.albedo.split(","):
                for seed in range(args.seeds):
                    key = DECODER_VARIANTS[name][0] if name in DECODER_VARIANTS else name  # same frames
                    capture = render_cached(args.captures, f"{key}_{scene_name}_{albedo}_{seed}_{args.camera}",
                                            lambda: simulate.render(rig, scene, image, conditions(albedo, seed)))
                    for method in args.methods.split(","):
                        if method == "baseband" and spec.phase_carriers:
                            continue  # the real-time path decodes stripes only
                        t0 = time.perf_counter()
                        result = Scanner(spec, rig.calibration, method=method,
                                         **DECODER_VARIANTS.get(name, (name, {}))[1]).scan(capture.image)
                        seconds = time.perf_counter() - t0
                        acc = accuracy(result, capture.truth, spec, rig.calibration)
                        row = dict(pattern=name, decoder=method, scene=scene_name, albedo=albedo, seed=seed,
                                   seconds=seconds, **acc.as_dict())
                        rows.append(row)
                        print(f"{name:22s} {method:9s} {scene_name:7s} {albedo:8s} {seed:4d} "
                              f"{100 * acc.stripe_accuracy:8.2f} {100 * acc.far_stripe:6.3f} {100 * acc.completeness:9.2f} "
                              f"{100 * acc.outliers:8.2f} {100 * acc.gross_outliers:6.3f} {acc.rms_mm:8.2f} {acc.median_mm:7.2f} "
                              f"{acc.oracle_median_mm:10.2f} {seconds:5.1f}", flush=True)
    Path(args.json).write_text(json.dumps({"camera": camera, "projector": projector, "rows": rows}, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(markdown_table(rows))


def clean_conditions(seed: int) -> simulate.Conditions:
    """Noise-free, linear projector, no blur, no ambient, uniform albedo 0.8, 8-bit output."""
    return simulate.Conditions.ideal().with_(albedo=simulate.UniformAlbedo(0.8), supersample=3, bit_depth=8,
                                             exposure=0.8, inverse_square=True, seed=seed)


def compare(rig: simulate.Rig, projector: tuple[int, int], args: argparse.Namespace) -> None:
    """Print and save the single-shot vs multi-shot table (`--compare`)."""
    keep = [p for p in args.patterns.split(",") if p]
    specs = {name: spec for name, spec in method_specs(projector).items() if not keep or name in keep}
    yardstick = patterns.thesis_spec(projector)
    conditions_of = {"clean": clean_conditions, "realistic": lambda seed: conditions("smooth", seed)}
    print(f"{'method':32s} {'frames':>6s} {'scene':7s} {'conditions':10s} {'complete%':>9s} {'outlier%':>8s} "
          f"{'rms mm':>8s} {'med mm':>7s} {'p95 mm':>7s} {'radius mm':>9s} {'rejected%':>9s} {'s':>5s}")
    rows = []
    for scene_name in [s for s in args.scenes.split(",") if s in ("sphere", "steps")]:
        scene = SCENES[scene_name]()
        for cond_name, make in conditions_of.items():
            for seed in range(args.seeds):
                for name, spec in specs.items():
                    (frames,), truth = render_captures(rig, scene, [spec], make(seed))
                    t0 = time.perf_counter()
                    result = Scanner(spec, rig.calibration).scan(frames)
                    seconds = time.perf_counter() - t0
                    acc = surface_accuracy(result, truth, stripe_depth(truth, yardstick, rig.calibration))
                    radius, rejected = (sphere_fit(result, truth, (0.0, 0.0, 800.0), 122.555)
                                        if scene_name == "sphere" else (float("nan"), float("nan")))
                    row = dict(method=name, frames=spec.frame_count, scene=scene_name, conditions=cond_name,
                               seed=seed, seconds=seconds, radius_mm=radius, fit_rejected=rejected,
                               **acc.as_dict())
                    rows.append(row)
                    print(f"{name:32s} {spec.frame_count:6d} {scene_name:7s} {cond_name:10s} "
                          f"{100 * acc.completeness:9.2f} {100 * acc.outliers:8.2f} {acc.rms_mm:8.2f} "
                          f"{acc.median_mm:7.2f} {acc.p95_mm:7.2f} {radius:9.2f} {100 * rejected:9.1f} {seconds:5.1f}", flush=True)
    Path(args.json).write_text(json.dumps({"camera": list(rig.calibration.camera.size), "projector": projector, "rows": rows}, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(compare_markdown(rows))


def compare_markdown(rows: list[dict]) -> str:
    """The `--compare` rows as the README's Markdown table.

    *PMP kept*: the median and the RMS error of multi-frequency PMP on the same scene,
    conditions and seed over this method's: the fraction of PMP's accuracy the method keeps.
    """
    pmp = {(r["scene"], r["conditions"], r["seed"]): r for r in rows if r["method"].startswith("PMP")}
    lines = ["| method | frames | scene | conditions | completeness | outliers | RMS (mm) | median (mm) "
             "| p95 (mm) | PMP kept (median / RMS) | sphere radius (mm) (fit rejected) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        radius = "" if r["radius_mm"] != r["radius_mm"] else f"{r['radius_mm']:.2f} ({100 * r['fit_rejected']:.1f} %)"
        reference = pmp.get((r["scene"], r["conditions"], r["seed"]))
        kept = "" if reference is None else (f"{100 * reference['median_mm'] / max(r['median_mm'], 1e-9):.1f} % / "
                                             f"{100 * reference['rms_mm'] / max(r['rms_mm'], 1e-9):.0f} %")
        lines.append(f"| {r['method']} | {r['frames']} | {r['scene']} | {r['conditions']} "
                     f"| {100 * r['completeness']:.1f} % | {100 * r['outliers']:.2f} % | {r['rms_mm']:.2f} "
                     f"| {r['median_mm']:.2f} | {r['p95_mm']:.2f} | {kept} | {radius} |")
    return "\n".join(lines) + "\n"


def render_cached(folder: str | None, key: str, render) -> simulate.Capture:
    """`render()`, or the capture saved under `key` in `folder` by an earlier run (then saved there)."""
    if folder is None:
        return render()
    path = Path(folder) / (key.replace(" ", "-") + ".npz")
    if path.exists():
        with np.load(path) as saved:
            return simulate.Capture(image=saved["image"], truth=truth_from(saved))
    capture = render()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, image=capture.image, **truth_arrays(capture.truth))
    return capture


#: How the tables name each `Scanner` method.
DECODER_NAMES = {"window": "sliscan window", "bandpass": "thesis band-pass", "baseband": "baseband (real time)"}


def markdown_table(rows: list[dict]) -> str:
    """The rows as the README's Markdown table."""
    lines = ["| pattern | decoder | scene | albedo | stripe accuracy | off > 1 stripe | completeness | outliers "
             "| gross outliers | RMS (mm) | median (mm) | oracle median (mm) | scan (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        decoder = DECODER_NAMES.get(r["decoder"], r["decoder"])
        lines.append(f"| {r['pattern']} | {decoder} | {r['scene']} | {r['albedo']} | {100 * r['stripe_accuracy']:.1f} % "
                     f"| {100 * r['far_stripe']:.2f} % | {100 * r['completeness']:.1f} % | {100 * r['outliers']:.2f} % | {100 * r['gross_outliers']:.3f} % "
                     f"| {r['rms_mm']:.1f} "
                     f"| {r['median_mm']:.2f} | {r['oracle_median_mm']:.2f} | {r['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
