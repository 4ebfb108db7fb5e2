"""Why a projector nonlinearity corrupts the thesis's carriers: row spectra from the virtual rig.

Renders the thesis's composite pattern (carriers 32, 64, 96, 128) and a pattern on carriers
planned free of third-order products (`photometry.plan_carriers`) on a fronto-parallel plane,
once through a linear projector and once through an uncorrected gamma of 2.2, with no noise.
It then takes the camera rows inside one stripe whose code has the LOWEST carrier off and all
the others on, and plots their mean power spectrum: whatever appears on the lowest carrier
there is a product of the others.  For the thesis's carriers, 64 - 32 = 96 - 64 = 128 - 96 = 32
fill it (the lost lowest carrier of fig. 3.15); for the planned ones, the products fall between
the carriers.  Saves a PNG (matplotlib, the ``plot`` extra).

    python benchmarks/carrier_spectra.py -o benchmarks/carrier_spectra.png
"""

from __future__ import annotations

import argparse

import numpy as np

from sliscan import patterns, photometry, simulate
from sliscan.demodulate import line_spectrum
from sliscan.evaluate import true_stripes

PROJECTOR = (1024, 768)


def stripe_rows_spectrum(spec: patterns.PatternSpec, gamma: float, rig: simulate.Rig) -> tuple[np.ndarray, np.ndarray]:
    """Mean power spectrum of the camera rows inside the stripe with only the lowest carrier off,
    rendered noise-free with no ambient light through a projector of this `gamma`.

    Returns frequencies in cycles per projector width and power, both ``(W // 2 + 1,)``.
    """
    low = int(np.argmin(spec.carriers))
    codes = patterns.code_bits(patterns.stripe_codes(spec), spec.bits)
    wanted = np.ones(spec.bits, dtype=np.uint8)
    wanted[low] = 0
    stripe = int(np.flatnonzero((codes == wanted).all(axis=1))[0])
    cond = simulate.Conditions(projector_gamma=gamma, full_well_e=None, bit_depth=None, ambient=0.0, supersample=1)
    shot = simulate.render(rig, simulate.plane_scene(), patterns.render_pattern(spec), cond)
    inside = true_stripes(shot.truth, spec) == stripe
    rows = np.flatnonzero(inside.mean(axis=1) > 0.95)
    rows = rows[2:-2]  # clear of the stripe borders' blur
    freqs, power = line_spectrum(shot.image[rows])
    scale = float(np.nanmedian(np.diff(shot.truth.proj[rows, :, 0], axis=1)))  # projector px per camera px
    return freqs * spec.orthogonal_lines / scale, power


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", default="benchmarks/carrier_spectra.png")
    parser.add_argument("--camera", default="1280x960")
    args = parser.parse_args()
    rig = simulate.virtual_rig(camera_size=tuple(int(v) for v in args.camera.split("x")), projector_size=PROJECTOR)
    specs = {"thesis carriers 32, 64, 96, 128": patterns.thesis_spec(PROJECTOR),
             "planned (order 3): " + ", ".join(f"{f:.0f}" for f in photometry.plan_carriers(1024, 4, order=3)):
                 patterns.thesis_spec(PROJECTOR, carriers=photometry.plan_carriers(1024, 4, order=3))}
    fig, axes = plt.subplots(len(specs), 1, figsize=(10, 7), sharex=True)
    for ax, (title, spec) in zip(axes, specs.items()):
        for gamma, style in ((1.0, dict(color="0.6", lw=1.0)), (2.2, dict(color="C3", lw=1.2))):
            f, power = stripe_rows_spectrum(spec, gamma, rig)
            label = "linear projector" if gamma == 1 else f"projector gamma {gamma:g}, uncorrected"
            ax.semilogy(f, power / power.max(), label=label, **style)
        low = min(spec.carriers)
        for c in spec.carriers:
            ax.axvline(c, color="C0", ls="--" if c == low else ":", lw=1)
        products, _ = photometry.carrier_products([c for c in spec.carriers if c != low], 3)
        hits = sorted({round(p) for p in products if abs(p - low) < 1e-6})
        note = f"products of the others on the (off) lowest carrier {low:.0f}: " + ("yes" if hits else "none")
        ax.set_title(f"{title}; stripe with only the lowest carrier off. {note}", fontsize=9)
        ax.set_ylim(1e-7, 2)
        ax.set_ylabel("row power (relative)")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1].set_xlim(0, 300)
    axes[-1].set_xlabel("frequency (cycles per 1024 projector px); dashed: the lowest carrier, dotted: the others")
    fig.tight_layout()
    fig.savefig(args.output, dpi=110)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
