"""The patterns the benchmarks set side by side, and their captures on the virtual rig.

Shared by `accuracy.py --compare` and `robustness.py`: the single-shot composite patterns (the
thesis's and sliscan's) and the multi-shot references (classic Gray code with and without phase
refinement, multi-frequency PMP), each built once here, and one render of a scene for any of
them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from sliscan import patterns, sequences, simulate
from sliscan.types import MULTI_FRAME_KINDS, PatternSpec


def method_specs(projector: tuple[int, int]) -> dict[str, PatternSpec]:
    """Single-shot composite patterns and the multi-shot references of `accuracy.py --compare`."""
    return {
        "CP thesis 4-bit": patterns.thesis_spec(projector),
        "CP sliscan 4-bit": patterns.default_spec(projector),
        "CP sliscan 4-bit + phase": patterns.phase_spec(projector),
        "Gray code 10-bit": PatternSpec(kind="graycode", projector_size=projector, orientation="rows"),
        "Gray code 7-bit + 4-step phase": PatternSpec(kind="graycode", projector_size=projector,
                                                      orientation="rows", code_width=8, steps=4),
        "PMP 1,8,64 x 4": PatternSpec(kind="pmp", projector_size=projector, orientation="rows",
                                      steps=4, frequencies=(1, 8, 64), a_p=0.5, b_p=0.5),
    }


def render_captures(rig: simulate.Rig, scene: simulate.Surface, specs: Sequence[PatternSpec],
                    conditions: simulate.Conditions) -> tuple[list[NDArray[np.float32]], simulate.GroundTruth]:
    """Camera frames of every pattern in `specs` on one scene, from one `simulate.render_sequence`
    call: the scene is traced once, and every frame of every pattern gets its own sensor noise
    (drawn in the order of `specs`; one pattern alone gets exactly what `simulate.render` or
    `simulate.render_sequence` of it alone gives).

    Returns
    -------
    frames : list parallel to `specs`
        What `Scanner.scan` takes: an (H, W) image for a composite pattern, (K, H, W) frames for
        a multi-frame one.
    truth : GroundTruth
        Common to all of them.
    """
    multi = [spec.kind in MULTI_FRAME_KINDS for spec in specs]
    drives = [sequences.render_frames(spec) if m else patterns.render_pattern(spec)[None]
              for spec, m in zip(specs, multi)]
    capture = simulate.render_sequence(rig, scene, np.concatenate(drives), conditions)
    ends = np.cumsum([len(d) for d in drives])
    frames = [capture.images[end - len(d):end] if m else capture.images[end - 1]
              for d, end, m in zip(drives, ends, multi)]
    return frames, capture.truth


def truth_arrays(truth: simulate.GroundTruth) -> dict[str, NDArray]:
    """A ground truth's arrays as ``truth_<field>`` keys, for `np.savez` beside its frames."""
    return {f"truth_{name}": value for name, value in vars(truth).items()}


def truth_from(saved: Mapping[str, NDArray]) -> simulate.GroundTruth:
    """The ground truth that `truth_arrays` saved (an open npz or a dict)."""
    return simulate.GroundTruth(**{key[6:]: saved[key] for key in saved if key.startswith("truth_")})

