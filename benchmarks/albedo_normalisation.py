"""Albedo normalisation before demodulation (issue 8, albedo edges): what each estimate does.

For sliscan's default 4-bit pattern and the window demodulator, scans the sphere and the steps
under the realistic conditions of `accuracy.py` (smooth albedo 0.15-1.0, or the sharp 40 mm
checker 0.25/0.9) after dividing the capture by each albedo estimate of
`sliscan.demodulate.normalise_albedo` (or none, or the true albedo blurred like the camera
blurs: a bound on what any estimate can give; and two diagnostics that split the steps
estimate's gap to it: the true albedo unblurred, and the true albedo's edges kept only where
the estimate found a step), and prints per capture, as Markdown:

* stripe accuracy: lit pixels decoded to exactly their true stripe, over lit pixels;
* wrong stripes (issue 8): valid lit pixels more than one stripe from the truth, over lit pixels;
* completeness: valid lit pixels over lit pixels;

then the means over scenes and seeds per albedo.  The whole `Scanner` runs (speckle and
narrow-run filters included); only its demodulation is replaced.

    python benchmarks/albedo_normalisation.py --captures /tmp/albedo-captures
    python benchmarks/albedo_normalisation.py --variants none,steps --seeds 0 --scenes sphere
    python benchmarks/albedo_normalisation.py --camera-blur 2 --albedo checker --variants steps,steps-blur-1,oracle
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.ndimage

from sliscan import patterns, simulate
from sliscan.demodulate import Demodulated, albedo_estimate, demodulate_window, detect_carriers, normalise_albedo
from sliscan.evaluate import true_stripes
from sliscan.pipeline import Scanner

from accuracy import conditions, render_cached

SCENES = {"sphere": simulate.sphere_scene, "steps": simulate.steps_scene}
#: variant -> (estimate, options of `normalise_albedo`); "none": no normalisation; "steps" is
#: the default of `demodulate_window` (its flat steps blurred, since the forty-fifth session);
#: "sharp-steps": none blurred; "steps-one-way": its lines read left to right only (the
#: detector until the fourteenth session); "steps-threshold-1": steps of a reflectance ratio of e
#: and more, sharp or not (until the forty-seventh session); "steps-0.8": the threshold of 0.8
#: without the concentration test (the forty-seventh session's); "steps-unsharp": without the
#: sharpness test; "steps-unconcentrated": without the concentration test; "steps-unflat":
#: without the flatness test under 1.0 (`STEP_FLAT_BELOW`); "steps-blur-1": the camera's blur
#: taken as 1 px, not measured on the capture (until the forty-ninth session; the same on a
#: 1 px camera); "steps-soft": every sharp step
#: blurred along the lines (a Gaussian of `SOFT_SIGMA` px, the thirteenth session's try); the
#: others: `_truth_gain`.
VARIANTS = {
    "none": (None, {}),
    "steps": ("steps", {}),
    "sharp-steps": ("sharp-steps", {}),
    "steps-one-way": ("steps", dict(both_ways=False)),
    "steps-threshold-1": ("steps", dict(threshold=1.0, sharpness=0.0, concentration=0.0)),
    "steps-0.8": ("steps", dict(threshold=0.8, concentration=0.0)),
    "steps-unsharp": ("steps", dict(sharpness=0.0)),
    "steps-unconcentrated": ("steps", dict(concentration=0.0)),
    "steps-unflat": ("steps", dict(flat_below=0.0)),
    "steps-blur-1": ("steps", dict(blur=1.0)),
    "steps-soft": ("steps-soft", {}),
    "closing": ("closing", {}),
    "envelopes": ("envelopes", {}),
    "guided": ("guided", {}),
    "notch-log": ("notch-log", {}),
    "notch": ("notch", {}),
    "oracle": ("oracle", {}),
    "oracle-sharp": ("oracle-sharp", {}),
    "oracle-found": ("oracle-found", {}),
}
#: Gaussian sigma (camera pixels) of the "steps-soft" variant's blur along the lines.
SOFT_SIGMA = 0.8


def _truth_gain(name: str, truth_albedo: np.ndarray, steps: np.ndarray, blur: float) -> np.ndarray:
    """The true albedo as the normalisation's gain: "oracle" blurred like the camera blurs
    (sigma `blur` px), "oracle-sharp" as rendered (pixels on an edge hold their areas' mean),
    "oracle-found" blurred but with only the edges within 4 px of a step of the `steps`
    estimate (along the lines): the estimate's edges, placed and sized exactly."""
    albedo = np.where(np.isfinite(truth_albedo), truth_albedo, 1.0).astype(np.float64)
    if name == "oracle-found":
        found = np.zeros(albedo.shape, bool)
        found[:, 1:] = np.abs(np.diff(np.log(steps), axis=1)) > 1e-6
        near = scipy.ndimage.maximum_filter1d(found, 9, axis=1)
        log_albedo = np.log(np.maximum(albedo, 1e-3))
        change = np.diff(log_albedo, axis=1, prepend=log_albedo[:, :1]) * near
        albedo = np.exp(log_albedo[:, :1] + np.cumsum(change, axis=1))
    if name != "oracle-sharp":
        albedo = scipy.ndimage.gaussian_filter(albedo, blur)
    return np.maximum(albedo, 1e-3).astype(np.float32)


class _Scanner(Scanner):
    """`Scanner` whose window demodulation divides the capture by a given albedo estimate."""

    def __init__(self, spec, calibration, estimate, options, truth_albedo, blur):
        super().__init__(spec, calibration)
        self._estimate, self._options, self._truth, self._blur = estimate, options, truth_albedo, blur

    def demodulate(self, image):
        img = np.asarray(image, dtype=np.float32)  # the default pattern: carriers along x
        carriers = detect_carriers(img, self.spec)
        if self._estimate is None:
            return demodulate_window(img, carriers, albedo=None), carriers
        if self._estimate.startswith("oracle"):
            steps = albedo_estimate(img, carriers, estimate="sharp-steps") if self._estimate == "oracle-found" else None
            gain = _truth_gain(self._estimate, self._truth, steps, self._blur)
            normalised = img / gain
        elif self._estimate == "steps-soft":
            gain = scipy.ndimage.gaussian_filter1d(albedo_estimate(img, carriers, estimate="sharp-steps"), SOFT_SIGMA, axis=1)
            normalised = img / gain
        else:
            normalised, gain = normalise_albedo(img, carriers, estimate=self._estimate, **self._options)
        d = demodulate_window(normalised, carriers, albedo=None)
        # back to image units, as demodulate_window does with its own estimate
        return Demodulated(amplitude=d.amplitude * gain[None], dc=d.dc * gain, residual=d.residual, misfit=d.misfit,
                           noise=d.noise * gain, offset=d.offset), carriers


def figures(result, truth, spec) -> tuple[float, float, float]:
    """(stripe accuracy, wrong-stripe rate, completeness) over lit pixels."""
    stripes = true_stripes(truth, spec)
    lit = stripes >= 0
    valid = result.valid & lit
    n = max(int(lit.sum()), 1)
    correct = valid & (result.stripe == stripes)
    wrong = valid & (np.abs(result.stripe.astype(np.int64) - stripes) > 1)
    return correct.sum() / n, wrong.sum() / n, valid.sum() / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="1296x972")
    parser.add_argument("--projector", default="1024x768")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--scenes", default="sphere,steps")
    parser.add_argument("--albedo", default="checker,smooth")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--captures", help="folder caching the rendered captures (npz, as accuracy.py --captures)")
    parser.add_argument("--camera-blur", type=float, default=1.0, help="the camera's Gaussian sigma (px)")
    args = parser.parse_args()
    camera = tuple(int(v) for v in args.camera.split("x"))
    projector = tuple(int(v) for v in args.projector.split("x"))
    rig = simulate.virtual_rig(camera_size=camera, projector_size=projector)
    spec = patterns.default_spec(projector)
    image = patterns.render_pattern(spec)
    print("| variant | scene | albedo | seed | stripe accuracy | wrong stripes (>1 off) | completeness | scan (s) |")
    print("|---|---|---|---|---|---|---|---|")
    totals: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for scene_name in args.scenes.split(","):
        scene = SCENES[scene_name]()
        for albedo in args.albedo.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                blurred = "" if args.camera_blur == 1.0 else f"_blur{args.camera_blur:g}"
                key = f"sliscan-4-bit_{scene_name}_{albedo}_{seed}_{args.camera}{blurred}"
                capture = render_cached(args.captures, key,
                                        lambda: simulate.render(rig, scene, image, conditions(albedo, seed).with_(
                                            camera_blur_px=args.camera_blur)))
                for name in args.variants.split(","):
                    estimate, options = VARIANTS[name]
                    scanner = _Scanner(spec, rig.calibration, estimate, options, capture.truth.albedo, args.camera_blur)
                    t0 = time.perf_counter()
                    result = scanner.scan(capture.image)
                    seconds = time.perf_counter() - t0
                    acc, wrong, complete = figures(result, capture.truth, spec)
                    totals.setdefault((name, albedo), []).append((acc, wrong, complete))
                    print(f"| {name} | {scene_name} | {albedo} | {seed} | {100 * acc:.2f} % | {100 * wrong:.3f} % | "
                          f"{100 * complete:.2f} % | {seconds:.1f} |", flush=True)
    print()
    print("| variant | albedo | mean stripe accuracy | mean wrong stripes | mean completeness |")
    print("|---|---|---|---|---|")
    for (name, albedo), vals in sorted(totals.items(), key=lambda kv: (kv[0][1], list(VARIANTS).index(kv[0][0]))):
        a, w, c = np.mean(vals, axis=0)
        print(f"| {name} | {albedo} | {100 * a:.2f} % | {100 * w:.3f} % | {100 * c:.2f} % |")


if __name__ == "__main__":
    main()
