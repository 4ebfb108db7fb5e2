"""What the 3D filters buy: scans with and without one, on captures rendered for the purpose.

``--filter narrow-runs`` (`outliers.remove_narrow_runs`): sliscan's default pattern and the
thesis's, single shot; gross outliers (`evaluate.gross_outliers`: more than three stripes off)
and completeness against the truth.

``--filter depth-edges`` (`outliers.remove_jump_edges`, then `outliers.remove_shadow_sides`):
the multi-shot references of `accuracy.py --compare` (`methods.method_specs`); completeness,
outliers (points farther than one stripe of the thesis's 4-bit pattern, as in that table), RMS,
median and 95th percentile error, and the sphere's fitted radius; with neither filter, with
the jump edges alone, and with both (the default).

Each on the sphere and the steps, under the accuracy benchmark's realistic conditions (smooth
or checker albedo) or its clean ones (``--albedo clean``), for each seed: the same capture
scanned by `Scanner` with the filter(s) off, then by the default `Scanner`.

    python benchmarks/outlier_filters.py --camera 1296x972 --seeds 1,2 --scenes sphere,steps --albedo smooth,checker
    python benchmarks/outlier_filters.py --camera 2592x1944 --seeds 7 --scenes sphere --albedo smooth
    python benchmarks/outlier_filters.py --filter depth-edges --seeds 1,2 --albedo smooth,checker,clean
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sliscan import patterns, simulate
from sliscan.evaluate import accuracy, sphere_fit, stripe_depth, surface_accuracy
from sliscan.pipeline import Scanner
from sliscan.types import MULTI_FRAME_KINDS, PatternSpec, ScanResult

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import SCENES, clean_conditions, conditions  # noqa: E402
from methods import method_specs, render_captures  # noqa: E402

PROJECTOR = (1024, 768)


def single_shot_figures(result: ScanResult, truth: simulate.GroundTruth, spec: PatternSpec, rig: simulate.Rig,
                        scene: str) -> str:
    """Gross outliers and completeness (%) of a composite pattern's scan."""
    acc = accuracy(result, truth, spec, rig.calibration)
    return f"{100 * acc.gross_outliers:8.4f} {100 * acc.completeness:7.2f}"


def surface_figures(result: ScanResult, truth: simulate.GroundTruth, spec: PatternSpec, rig: simulate.Rig,
                    scene: str) -> str:
    """Completeness, outliers (%), RMS, median, p95 error and fitted sphere radius (mm; sphere
    scene) of any scan."""
    acc = surface_accuracy(result, truth, stripe_depth(truth, patterns.thesis_spec(PROJECTOR), rig.calibration))
    radius = sphere_fit(result, truth, (0.0, 0.0, 800.0), 122.555)[0] if scene == "sphere" else float("nan")
    return (f"{100 * acc.completeness:7.2f} {100 * acc.outliers:6.3f} {acc.rms_mm:6.2f} {acc.median_mm:6.3f} "
            f"{acc.p95_mm:6.2f} {radius:7.2f}")


#: Per filter: the `Scanner` options of each column (the last one the default), their labels,
#: the figures' header and the function that gives them.
FILTERS = {
    "narrow-runs": ([dict(remove_narrow_runs=False), {}], ["without", "with"], "gross %  compl %",
                    single_shot_figures),
    "depth-edges": ([dict(remove_jump_edges=False, remove_shadow_sides=False), dict(remove_shadow_sides=False), {}],
                    ["neither", "jump edges", "both"], "compl % outl %    RMS    med    p95  radius", surface_figures),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--filter", choices=sorted(FILTERS), default="narrow-runs")
    parser.add_argument("--camera", default="1296x972")
    parser.add_argument("--seeds", default="1,2", help="comma-separated seeds (pick ones no tuning used)")
    parser.add_argument("--scenes", default="sphere,steps")
    parser.add_argument("--albedo", default="smooth,checker", help="smooth, checker (realistic) or clean")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=PROJECTOR)
    options, labels, header, figures_of = FILTERS[args.filter]
    if args.filter == "narrow-runs":
        specs = {"sliscan 4-bit": patterns.default_spec(PROJECTOR), "thesis 4-bit": patterns.thesis_spec(PROJECTOR)}
    else:
        specs = {name: spec for name, spec in method_specs(PROJECTOR).items() if spec.kind in MULTI_FRAME_KINDS}
    print(f"{'pattern':31s} {'scene':7s} {'albedo':8s} {'seed':>4s} | " + " | ".join(f"{label}: {header}"
                                                                                 for label in labels))
    for name, spec in specs.items():
        for scene_name in args.scenes.split(","):
            scene = SCENES[scene_name]()
            for albedo in args.albedo.split(","):
                for seed in (int(v) for v in args.seeds.split(",")):
                    made = clean_conditions(seed) if albedo == "clean" else conditions(albedo, seed)
                    (frames,), truth = render_captures(rig, scene, [spec], made)
                    figures = [figures_of(Scanner(spec, rig.calibration, **option).scan(frames), truth, spec, rig,
                                          scene_name) for option in options]
                    print(f"{name:31s} {scene_name:7s} {albedo:8s} {seed:4d} | " + " | ".join(figures), flush=True)


if __name__ == "__main__":
    main()
