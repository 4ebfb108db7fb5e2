"""What the narrow-run filter (`outliers.remove_narrow_runs`) buys: gross outliers and
completeness of single-shot scans with and without it, on captures rendered for the purpose.

For sliscan's default pattern and the thesis's, on the sphere and the steps, under the accuracy
benchmark's realistic conditions (smooth or checker albedo), for each seed: the same capture
scanned by `Scanner(remove_narrow_runs=False)` and by the default `Scanner`; gross outliers
(`evaluate.gross_outliers`: more than three stripes off) and completeness against the truth.

    python benchmarks/outlier_filters.py --camera 1296x972 --seeds 1,2 --scenes sphere,steps --albedo smooth,checker
    python benchmarks/outlier_filters.py --camera 2592x1944 --seeds 7 --scenes sphere --albedo smooth
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sliscan import patterns, simulate
from sliscan.evaluate import accuracy
from sliscan.pipeline import Scanner

sys.path.insert(0, str(Path(__file__).parent))
from accuracy import SCENES, conditions  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="1296x972")
    parser.add_argument("--seeds", default="1,2", help="comma-separated seeds (pick ones no tuning used)")
    parser.add_argument("--scenes", default="sphere,steps")
    parser.add_argument("--albedo", default="smooth,checker")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=(1024, 768))
    specs = {"sliscan 4-bit": patterns.default_spec((1024, 768)), "thesis 4-bit": patterns.thesis_spec((1024, 768))}
    print(f"{'pattern':14s} {'scene':7s} {'albedo':8s} {'seed':>4s} | {'without: gross %':>16s} {'complete %':>10s} "
          f"| {'with: gross %':>13s} {'complete %':>10s}")
    for name, spec in specs.items():
        for scene_name in args.scenes.split(","):
            scene = SCENES[scene_name]()
            for albedo in args.albedo.split(","):
                for seed in (int(v) for v in args.seeds.split(",")):
                    capture = simulate.render(rig, scene, patterns.render_pattern(spec), conditions(albedo, seed))
                    figures = []
                    for narrow in (False, True):
                        result = Scanner(spec, rig.calibration, remove_narrow_runs=narrow).scan(capture.image)
                        acc = accuracy(result, capture.truth, spec, rig.calibration)
                        figures.append(f"{100 * acc.gross_outliers:16.4f} {100 * acc.completeness:10.2f}")
                    print(f"{name:14s} {scene_name:7s} {albedo:8s} {seed:4d} | {figures[0]} | {figures[1]}", flush=True)


if __name__ == "__main__":
    main()
