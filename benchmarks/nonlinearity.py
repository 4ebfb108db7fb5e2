"""Projector nonlinearity on the virtual rig: the estimators, and thesis vs planned carriers.

(a) The characterisation estimators against the rig's known values: `photometry.estimate_gamma`
    on a full-range sine (plain matte target, uniform albedo 0.8) for several projector gammas
    and scenes, and `photometry.measure_rolloff` on a gamma pre-corrected carrier-only pattern
    against the closed-form transfer of the rig's blur (`evaluate.carrier_transfer`).
(b) Stripe accuracy (`evaluate.accuracy`: lit pixels decoded to their true stripe) and
    completeness of 4-bit composite patterns on the thesis's carriers (32, 64, 96, 128), on
    sliscan's default (the same, reversed over the bits) and on carriers planned free of the
    products of order 2 and 3 (`photometry.plan_carriers`, most significant bit on the highest),
    under each nonlinearity on a uniform-albedo tilted plane, and on the realistic scenes.

    python benchmarks/nonlinearity.py --quick            # one seed, ~5 min on 2 cores
    python benchmarks/nonlinearity.py --seeds 2 --json benchmarks/nonlinearity.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from sliscan import evaluate, patterns, photometry, simulate
from sliscan._validate import InputError
from sliscan.pipeline import Scanner

PROJECTOR = (1024, 768)
SCENES = {"plane": simulate.plane_scene, "tilted": simulate.tilted_plane_scene, "sphere": simulate.sphere_scene,
          "steps": simulate.steps_scene}


def pattern_specs() -> dict[str, patterns.PatternSpec]:
    """The 4-bit patterns compared: all skip the zero code except the thesis's."""
    width = PROJECTOR[0]
    specs = {"thesis": patterns.thesis_spec(PROJECTOR), "default": patterns.default_spec(PROJECTOR)}
    for order in (2, 3):
        planned = tuple(reversed(photometry.plan_carriers(width, 4, order=order)))
        specs[f"planned o{order}"] = patterns.default_spec(PROJECTOR, carriers=planned)
    return specs


#: Nonlinearity cases of part (b): (name, scene, albedo, projector gamma, pre-correction, exposure).
CASES = [
    ("linear (control)", "tilted", "uniform", 2.2, 2.2, 0.8),
    ("gamma 2.2 uncorrected", "tilted", "uniform", 2.2, 1.0, 0.8),
    ("gamma 2.6 uncorrected", "tilted", "uniform", 2.6, 1.0, 0.8),
    ("pre-correction 1.9 for 2.2", "tilted", "uniform", 2.2, 1.9, 0.8),
    ("pre-correction 2.5 for 2.2", "tilted", "uniform", 2.2, 2.5, 0.8),
    ("saturation (exposure 1.6)", "tilted", "uniform", 2.2, 2.2, 1.6),
    ("realistic sphere smooth", "sphere", "smooth", 2.2, 1.0, 0.8),
    ("realistic sphere checker", "sphere", "checker", 2.2, 1.0, 0.8),
    ("realistic steps smooth", "steps", "smooth", 2.2, 1.0, 0.8),
    ("realistic steps checker", "steps", "checker", 2.2, 1.0, 0.8),
]


def albedo(name: str, seed: int):
    return {"uniform": simulate.UniformAlbedo(0.8), "smooth": simulate.SmoothAlbedo(seed=seed),
            "checker": simulate.CheckerAlbedo()}[name]


def gamma_rows(rig: simulate.Rig, gammas: list[float], scenes: list[str], seeds: int, supersample: int) -> list[dict]:
    spec = photometry.sine_target(PROJECTOR)
    image = patterns.render_pattern(spec)
    rows = []
    for scene in scenes:
        for gamma in gammas:
            for seed in range(seeds):
                cond = simulate.Conditions(projector_gamma=gamma, supersample=supersample, seed=seed)
                fit = photometry.estimate_gamma(simulate.render(rig, SCENES[scene](), image, cond).image, spec)
                lut = float(np.max(np.abs(np.asarray(fit.response) - photometry.gamma_response(gamma))))
                rows.append(dict(scene=scene, gamma=gamma, seed=seed, estimate=fit.gamma, error=fit.gamma - gamma,
                                 spread=fit.spread, response_error=lut))
                print(f"gamma  {scene:7s} true {gamma:.2f} seed {seed}: estimate {fit.gamma:.3f} "
                      f"(error {fit.gamma - gamma:+.3f}, tiles +/- {fit.spread:.3f}), response table max error "
                      f"{lut:.4f}", flush=True)
    return rows


def rolloff_rows(rig: simulate.Rig, blurs: list[float], seeds: int, supersample: int) -> list[dict]:
    rows = []
    for name, spec in pattern_specs().items():
        for corrected in (True, False):
            carrier_only = spec.with_(kind="carrier_only", gamma=2.2 if corrected else 1.0, weights=(1.0,) * 4,
                                      b_p=0.125)
            image = patterns.render_pattern(carrier_only)
            for blur in blurs:
                for seed in range(seeds):
                    cond = simulate.Conditions(projector_blur_px=blur, camera_blur_px=blur, supersample=supersample,
                                               seed=seed)
                    shot = simulate.render(rig, simulate.plane_scene(), image, cond)
                    measured = np.asarray(photometry.measure_rolloff(shot.image, carrier_only).attenuation)
                    truth = evaluate.carrier_transfer(carrier_only, cond, shot.truth)
                    error = float(np.max(np.abs(measured / truth - 1)))
                    rows.append(dict(pattern=name, corrected=corrected, blur=blur, seed=seed,
                                     measured=measured.tolist(), truth=truth.tolist(), max_relative_error=error))
                    print(f"rolloff {name:10s} {'pre-corrected' if corrected else 'uncorrected  '} blur {blur:.1f} "
                          f"seed {seed}: measured {np.round(measured, 3).tolist()} true {np.round(truth, 3).tolist()} "
                          f"max error {100 * error:.1f} %", flush=True)
    return rows


def decode_rows(rig: simulate.Rig, seeds: int, supersample: int) -> list[dict]:
    rows = []
    for case, scene, texture, gamma, precorrection, exposure in CASES:
        surface = SCENES[scene]()
        for name, spec in pattern_specs().items():
            spec = spec.with_(gamma=precorrection)
            image = patterns.render_pattern(spec)
            for seed in range(seeds):
                cond = simulate.Conditions(albedo=albedo(texture, seed), projector_gamma=gamma, exposure=exposure,
                                           supersample=supersample, seed=seed)
                shot = simulate.render(rig, surface, image, cond)
                t0 = time.perf_counter()
                try:
                    result = Scanner(spec, rig.calibration).scan(shot.image)
                except InputError as exc:  # the carriers were not found: nothing decoded
                    print(f"decode {case:28s} {name:10s} seed {seed}: scan failed ({exc})", flush=True)
                    rows.append(dict(case=case, pattern=name, seed=seed, stripe_accuracy=0.0, completeness=0.0,
                                     wrong_stripe=0.0, saturated=float(np.mean(shot.image >= 1.0)), failed=str(exc)))
                    continue
                acc = evaluate.accuracy(result, shot.truth, spec, rig.calibration)
                rows.append(dict(case=case, pattern=name, seed=seed, stripe_accuracy=acc.stripe_accuracy,
                                 completeness=acc.completeness, wrong_stripe=acc.wrong_stripe,
                                 saturated=float(np.mean(shot.image >= 1.0)), seconds=time.perf_counter() - t0))
                print(f"decode {case:28s} {name:10s} seed {seed}: stripes right {100 * acc.stripe_accuracy:5.1f} % "
                      f"complete {100 * acc.completeness:5.1f} % wrong {100 * acc.wrong_stripe:4.1f} % "
                      f"saturated {100 * rows[-1]['saturated']:4.1f} %", flush=True)
    return rows


def summary(rows: list[dict]) -> str:
    """Part (b) as a Markdown table: mean over seeds, one column pair per pattern."""
    names = list(pattern_specs())
    head = "| case | " + " | ".join(f"{n}: right / complete" for n in names) + " |"
    lines = [head, "|---" * (len(names) + 1) + "|"]
    for case, *_ in CASES:
        cells = []
        for name in names:
            sel = [r for r in rows if r["case"] == case and r["pattern"] == name]
            if not sel:
                cells.append("-")
                continue
            right = 100 * np.mean([r["stripe_accuracy"] for r in sel])
            complete = 100 * np.mean([r["completeness"] for r in sel])
            cells.append(f"{right:.1f} % / {complete:.1f} %")
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", default="640x480")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--supersample", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="one seed, fewer gammas and blurs")
    parser.add_argument("--json", help="write every row as JSON to this file")
    args = parser.parse_args()
    seeds = 1 if args.quick else args.seeds
    rig = simulate.virtual_rig(camera_size=tuple(int(v) for v in args.camera.split("x")), projector_size=PROJECTOR)
    gammas = [1.8, 2.2, 2.6] if args.quick else [1.8, 2.0, 2.2, 2.4, 2.6]
    blurs = [1.0] if args.quick else [0.5, 1.0, 1.5]
    out = {"camera": args.camera, "seeds": seeds, "supersample": args.supersample,
           "gamma": gamma_rows(rig, gammas, ["plane", "sphere", "steps"], seeds, args.supersample),
           "rolloff": rolloff_rows(rig, blurs, seeds, args.supersample),
           "decode": decode_rows(rig, seeds, args.supersample)}
    errors = np.abs([r["error"] for r in out["gamma"]])
    print(f"\ngamma: max |error| {errors.max():.3f}, median {np.median(errors):.3f} over {errors.size} captures")
    for corrected in (True, False):
        sel = [r["max_relative_error"] for r in out["rolloff"] if r["corrected"] == corrected]
        print(f"roll-off ({'pre-corrected' if corrected else 'uncorrected'} carrier-only): max relative error "
              f"{100 * max(sel):.1f} %")
    print("\n" + summary(out["decode"]))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
