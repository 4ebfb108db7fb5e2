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
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from sliscan import patterns, simulate
from sliscan.evaluate import accuracy
from sliscan.pipeline import Scanner

SCENES = {
    "sphere": simulate.sphere_scene,
    "steps": simulate.steps_scene,
    "tilted": simulate.tilted_plane_scene,
}


def pattern_specs(projector: tuple[int, int], quick: bool) -> dict[str, patterns.PatternSpec]:
    """The patterns compared: the thesis's, sliscan's default, and the same with more bits.

    More bits use carriers spread evenly up to the thesis's highest (an 8-pixel period in
    the projector, which the default rig's camera resolves with 2.5 pixels per projector
    pixel), so the window grows with the number of bits.
    """
    width = projector[0]
    specs = {"thesis 4-bit": patterns.thesis_spec(projector), "sliscan 4-bit": patterns.default_spec(projector)}
    if not quick:
        for bits in (6, 8):
            carriers = tuple(k * width / 8 / bits for k in range(1, bits + 1))
            specs[f"thesis-style {bits}-bit"] = patterns.PatternSpec(
                projector_size=projector, bits=bits, carriers=carriers, weights=(1.0,) * bits, a_p=0.5, b_p=0.5 / bits)
            specs[f"sliscan {bits}-bit"] = patterns.default_spec(projector, bits=bits)
    return specs


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
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--albedo", default="smooth,checker")
    parser.add_argument("--methods", default="window,bandpass")
    parser.add_argument("--json", default="benchmarks/accuracy.json")
    parser.add_argument("--markdown", help="also write the table as Markdown (as in the README) to this file")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    projector = tuple(int(v) for v in args.projector.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    rows = []
    header = (f"{'pattern':22s} {'decoder':9s} {'scene':7s} {'albedo':8s} {'seed':>4s} {'stripe%':>8s} "
              f"{'complete%':>9s} {'outlier%':>8s} {'rms mm':>8s} {'med mm':>7s} {'oracle med':>10s} {'s':>5s}")
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
                    capture = simulate.render(rig, scene, image, conditions(albedo, seed))
                    for method in args.methods.split(","):
                        t0 = time.perf_counter()
                        result = Scanner(spec, rig.calibration, method=method).scan(capture.image)
                        seconds = time.perf_counter() - t0
                        acc = accuracy(result, capture.truth, spec, rig.calibration)
                        row = dict(pattern=name, decoder=method, scene=scene_name, albedo=albedo, seed=seed,
                                   seconds=seconds, **acc.as_dict())
                        rows.append(row)
                        print(f"{name:22s} {method:9s} {scene_name:7s} {albedo:8s} {seed:4d} "
                              f"{100 * acc.stripe_accuracy:8.2f} {100 * acc.completeness:9.2f} "
                              f"{100 * acc.outliers:8.2f} {acc.rms_mm:8.2f} {acc.median_mm:7.2f} "
                              f"{acc.oracle_median_mm:10.2f} {seconds:5.1f}", flush=True)
    Path(args.json).write_text(json.dumps({"camera": camera, "projector": projector, "rows": rows}, indent=1))
    if args.markdown:
        Path(args.markdown).write_text(markdown_table(rows))


def markdown_table(rows: list[dict]) -> str:
    """The rows as the README's Markdown table."""
    lines = ["| pattern | decoder | scene | albedo | stripe accuracy | completeness | outliers | RMS (mm) "
             "| median (mm) | oracle median (mm) | scan (s) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        decoder = "sliscan window" if r["decoder"] == "window" else "thesis band-pass"
        lines.append(f"| {r['pattern']} | {decoder} | {r['scene']} | {r['albedo']} | {100 * r['stripe_accuracy']:.1f} % "
                     f"| {100 * r['completeness']:.1f} % | {100 * r['outliers']:.2f} % | {r['rms_mm']:.1f} "
                     f"| {r['median_mm']:.2f} | {r['oracle_median_mm']:.2f} | {r['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
