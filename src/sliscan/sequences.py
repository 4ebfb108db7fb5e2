"""Multi-frame patterns (``pmp``, ``graycode``): their images, files, capture checks and decoding.

The pattern kinds differ in how they code the projector (`sliscan.pmp`, `sliscan.graycode`);
everything around that is shared here: the projected images of a spec, writing them beside the
PatternSpec JSON (its ``"frames"`` key lists them in projection order), checking a capture
(the number of frames, their shapes and types) and decoding every coded direction into a
`ProjectorMap`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sliscan import graycode, pmp
from sliscan._validate import InputError, atomic_path, check_image, write_images
from sliscan.pmp import ProjectorMap
from sliscan.types import MULTI_FRAME_KINDS, PatternSpec

_FRAMES: dict[str, Callable[[PatternSpec], NDArray[np.float32]]] = {
    "pmp": pmp.pattern_frames,
    "graycode": graycode.pattern_frames,
}
_DECODERS: dict[str, Callable[..., ProjectorMap]] = {
    "pmp": pmp.decode_pmp,
    "graycode": graycode.decode_graycode,
}


def _check_kind(spec: PatternSpec) -> None:
    if spec.kind not in MULTI_FRAME_KINDS:
        raise InputError(f"a {spec.kind} pattern is one image, not a sequence (multi-frame kinds: {MULTI_FRAME_KINDS})")


def describe_frames(spec: PatternSpec) -> str:
    """How a multi-frame spec's frames are made up, for messages.

    >>> describe_frames(PatternSpec(kind="pmp", steps=4, frequencies=(1, 8, 64), b_p=0.5))
    '1 direction x 3 frequencies x 4 steps'
    >>> describe_frames(PatternSpec(kind="graycode", orientation="both"))
    '10 column and 10 row bits as pattern/inverse pairs, white, black'
    """
    _check_kind(spec)
    if spec.kind == "pmp":
        n = len(spec.directions)
        return (f"{n} direction{'s' if n > 1 else ''} x {len(spec.frequencies)} "
                f"frequenc{'ies' if len(spec.frequencies) > 1 else 'y'} x {spec.steps} steps")
    names = {"columns": "column", "rows": "row"}
    bits = " and ".join(f"{spec.gray_bits(d)} {names[d]}" for d in spec.directions)
    phase = f", {spec.steps} phase steps per direction" if spec.steps else ""
    return f"{bits} bits as pattern/inverse pairs, white, black{phase}"


def render_frames(spec: PatternSpec) -> NDArray[np.float32]:
    """Every projected image of a multi-frame spec, in projection order: ``(frame_count, H_p, W_p)``
    float32 in [0, 1] on the 1/255 grid."""
    _check_kind(spec)
    return _FRAMES[spec.kind](spec)


def indexed_paths(path: str | os.PathLike, count: int) -> list[Path]:
    """One file name per frame: ``DIR/cap.png`` -> ``DIR/cap_00.png``, ``DIR/cap_01.png``, ...
    with as many digits as `count` needs (at least 2), so the names sort in frame order.

    >>> [p.name for p in indexed_paths("out/cap.png", 3)]
    ['cap_00.png', 'cap_01.png', 'cap_02.png']
    """
    path = Path(path)
    digits = max(2, len(str(count - 1)))
    return [path.with_name(f"{path.stem}_{k:0{digits}d}{path.suffix}") for k in range(count)]


def frame_paths(path: str | os.PathLike, spec: PatternSpec) -> list[Path]:
    """The frame images `save_sequence` writes beside the JSON `path`: ``DIR/pmp.json`` ->
    ``DIR/pmp_00.png``, ``DIR/pmp_01.png``, ... (`indexed_paths`)."""
    return indexed_paths(Path(path).with_suffix(".png"), spec.frame_count)


def save_sequence(path: str | os.PathLike, spec: PatternSpec) -> tuple[list[Path], Path]:
    """Write the images of a multi-frame spec (8-bit PNG) and its PatternSpec JSON.

    ``DIR/pmp.json`` gets ``DIR/pmp_00.png``, ``DIR/pmp_01.png``, ... (as many digits as the
    count needs), listed in projection order under the JSON's ``"frames"`` key.  Every file is
    written to a temporary name first and all are renamed at the end, so a failure leaves none.

    Returns
    -------
    frame_paths : list of Path
    json_path : Path
    """
    json_path = Path(path)
    if json_path.suffix.lower() != ".json":
        raise InputError(f"{json_path}: give the JSON file name (e.g. pmp.json); the frames go beside it")
    paths = frame_paths(json_path, spec)
    spec = spec.with_(frames=tuple(p.name for p in paths))
    with atomic_path(json_path) as tmp:
        tmp.write_text(json.dumps(spec.to_dict(), indent=2) + "\n")
        write_images(paths, render_frames(spec))
    return paths, json_path


def check_frames(frames: Sequence[ArrayLike] | ArrayLike, spec: PatternSpec, *,
                 shape: tuple[int, int] | None = None) -> NDArray[np.float32]:
    """A capture of a multi-frame pattern as one ``(frame_count, H, W)`` float32 array in [0, 1].

    Parameters
    ----------
    frames : sequence of (H, W) arrays, or a (K, H, W) array
        uint8, uint16 or float in [0, 1], in the spec's order; never modified.
    spec : PatternSpec
        A multi-frame spec.
    shape : (H, W), optional
        Required frame shape (the camera's); default: the first frame's.

    Raises
    ------
    InputError
        On the wrong number of frames (naming how many the spec needs and why), a frame of
        another shape or type, or non-finite values.
    """
    _check_kind(spec)
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        raise InputError(f"a {spec.kind} capture is a sequence of {spec.frame_count} frames "
                         f"({describe_frames(spec)}), got one image")
    frames = list(frames)
    if len(frames) != spec.frame_count:
        raise InputError(f"a {spec.kind} capture needs {spec.frame_count} frames ({describe_frames(spec)}), "
                         f"got {len(frames)}")
    first = check_image("frame 0", frames[0], shape=shape)
    return np.stack([first] + [check_image(f"frame {k}", frames[k], shape=first.shape)
                               for k in range(1, len(frames))])


def decode_frames(frames: Sequence[ArrayLike] | ArrayLike, spec: PatternSpec, *,
                  shape: tuple[int, int] | None = None, **options: Any) -> dict[str, ProjectorMap]:
    """Every coded projector coordinate of a capture: ``{"columns": map, "rows": map}`` (the
    directions the spec codes), each a `ProjectorMap` per camera pixel.

    This is what calibration needs from a ``"both"`` sequence: `xp` and `yp` of every pixel.

    Parameters
    ----------
    frames, spec, shape
        As for `check_frames`.
    **options
        Thresholds of `pmp.decode_pmp` or `graycode.decode_graycode`.
    """
    stack = check_frames(frames, spec, shape=shape)
    return {direction: _DECODERS[spec.kind](stack, spec, direction, **options) for direction in spec.directions}

