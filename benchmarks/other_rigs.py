"""The stripe patterns on rigs and scenes no setting was chosen on.

Ten captures the accuracy benchmark does not have: 1600x1200, 1280x960 and 1024x768 cameras
(the 1024x768 projector of the thesis), an upright cylinder, two spheres, a box and a lying
cylinder before a wall, steps, the sphere, a plane turned 40 degrees about the vertical,
checkers of 25-50 mm (reflectances 0.2-0.3 / 0.9) or a smooth albedo, blur of 1-2.5 px on both
sides, ambient light 5-20 %, each with its own seed; gamma 2.2 uncorrected, shot and read
noise, 8 bits, as in the accuracy benchmark.  The fifty-fourth session built it to check its
changes away from the scenes it had measured on; every later change to the decoder is measured
here too (docs/accuracy.md, "A shadow between two edges").

    python benchmarks/other_rigs.py --captures /tmp/other-rigs              # ~15 min rendering, then ~4 min
    python benchmarks/other_rigs.py --captures /tmp/other-rigs --against benchmarks/other-rigs.json

Prints one row per capture and pattern (completeness, right stripes, stripes more than one off,
gross outliers, all % of the lit pixels; RMS and median error in mm); ``--against`` prints each
figure as ``before -> after`` against an earlier run's JSON.  A pattern whose carriers the
capture does not show is refused, as `sliscan scan` refuses it, and listed so.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from methods import render_captures, truth_arrays, truth_from
from sliscan import InputError, patterns, simulate
from sliscan.evaluate import accuracy
from sliscan.pipeline import Scanner


def checker(square_mm: float, low: float = 0.25) -> simulate.CheckerAlbedo:
    """A checker of `square_mm` squares, reflectance `low` / 0.9."""
    return simulate.CheckerAlbedo(square_mm=square_mm, low=low, high=0.9)


#: name: (camera, scene, albedo (None: smooth 0.15-1.0 of the capture's seed), blur px, ambient, seed)
CAPTURES = {
    "cyl1600_b25": ((1600, 1200), lambda: simulate.cylinder_scene(), checker(40), 2.5, 0.1, 0),
    "cyl1600_b15": ((1600, 1200), lambda: simulate.cylinder_scene(radius_mm=80), checker(30), 1.5, 0.1, 1),
    "obj1600_b15": ((1600, 1200), lambda: simulate.objects_scene(), None, 1.5, 0.1, 2),
    "obj1280_chk": ((1280, 960), lambda: simulate.objects_scene(distance_mm=750), checker(25), 1.0, 0.15, 3),
    "steps1280_chk": ((1280, 960), lambda: simulate.steps_scene(), checker(30, 0.2), 1.2, 0.1, 4),
    "sph1280_chk": ((1280, 960), lambda: simulate.sphere_scene(), checker(25), 1.5, 0.2, 5),
    "tilt1600_y40": ((1600, 1200), lambda: simulate.tilted_plane_scene(40, axis="y"), checker(35), 1.0, 0.1, 6),
    "cyl1024_b2": ((1024, 768), lambda: simulate.cylinder_scene(radius_mm=120), None, 2.0, 0.1, 7),
    "obj1600_b25": ((1600, 1200), lambda: simulate.objects_scene(distance_mm=850), checker(50, 0.3), 2.5, 0.1, 8),
    "sph1600_b2": ((1600, 1200), lambda: simulate.sphere_scene(), None, 2.0, 0.05, 9),
}
PATTERNS = {"thesis": patterns.thesis_spec, "sliscan": patterns.default_spec}
FIGURES = (("comp", "completeness", 100), ("right", "stripe_accuracy", 100), ("far", "far_stripe", 100),
           ("gross", "gross_outliers", 100), ("rms", "rms_mm", 1), ("median", "median_mm", 1))


def captures(name: str, folder: str | None, specs: list[patterns.PatternSpec]) -> tuple[list, simulate.GroundTruth]:
    """Every pattern's frame of capture `name` and its truth, rendered or read from `folder`."""
    camera, scene, albedo, blur, ambient, seed = CAPTURES[name]
    path = Path(folder) / f"{name}.npz" if folder else None
    if path is not None and path.exists():
        with np.load(path) as saved:
            return list(saved["frames"]), truth_from(saved)
    rig = simulate.virtual_rig(camera_size=camera, projector_size=(1024, 768))
    conditions = simulate.Conditions(albedo=albedo or simulate.SmoothAlbedo(low=0.15, high=1.0, seed=seed),
                                     ambient=ambient, projector_gamma=2.2, projector_blur_px=blur,
                                     camera_blur_px=blur, seed=seed)
    frames, truth = render_captures(rig, scene(), specs, conditions)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, frames=np.array(frames), **truth_arrays(truth))
    return frames, truth


def measure(name: str, folder: str | None) -> list[dict]:
    """One row per pattern of capture `name`."""
    rig = simulate.virtual_rig(camera_size=CAPTURES[name][0], projector_size=(1024, 768))
    specs = [make(rig.calibration.projector.size) for make in PATTERNS.values()]
    frames, truth = captures(name, folder, specs)
    rows = []
    for pattern, spec, frame in zip(PATTERNS, specs, frames):
        row = dict(capture=name, pattern=pattern)
        try:
            result = Scanner(spec, rig.calibration).scan(frame)
        except InputError as error:
            rows.append(dict(row, refused=str(error)))
            continue
        found = accuracy(result, truth, spec, rig.calibration)
        rows.append(dict(row, **{key: float(getattr(found, field)) for key, field, _ in FIGURES}))
    return rows


def line(row: dict, before: dict | None) -> str:
    """A printed row, with `before`'s figures where given."""
    head = f"{row['capture']:14s} {row['pattern']:8s}"
    if "refused" in row:
        return f"{head} refused: {row['refused']}"
    cells = []
    for key, _, scale in FIGURES:
        now = f"{scale * row[key]:.3f}" if key in ("far", "gross") else f"{scale * row[key]:.1f}"
        if before is not None and key in before:
            was = f"{scale * before[key]:.3f}" if key in ("far", "gross") else f"{scale * before[key]:.1f}"
            now = f"{was} -> {now}"
        cells.append(f"{key} {now}")
    return f"{head} " + "  ".join(cells)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--captures", help="folder caching the rendered captures (npz)")
    parser.add_argument("--only", default=",".join(CAPTURES), help="comma-separated capture names")
    parser.add_argument("--json", default="benchmarks/other-rigs.json")
    parser.add_argument("--against", help="an earlier run's JSON: print its figures beside these")
    args = parser.parse_args()
    earlier = {}
    if args.against:
        earlier = {(r["capture"], r["pattern"]): r for r in json.loads(Path(args.against).read_text())["rows"]}
    rows = []
    for name in args.only.split(","):
        for row in measure(name, args.captures):
            rows.append(row)
            print(line(row, earlier.get((row["capture"], row["pattern"]))), flush=True)
    Path(args.json).write_text(json.dumps({"rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
