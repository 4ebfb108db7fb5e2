"""The interactive 3D view of a scan (issue 10): a plotly WebGL figure that works offline.

A scan is an organised grid (one point per camera pixel), so the view is a mesh: every square
of four neighbouring valid pixels gives two triangles, except across a depth discontinuity (a
triangle whose longest edge exceeds `MAX_EDGE_FACTOR` times the median, e.g. from a sphere to
the wall behind it).  A large scan is decimated first by a grid stride: every `stride`-th pixel
in rows and columns, the smallest stride that keeps at most `MESH_BUDGET` vertices, which keeps
the grid's structure (and so the mesh) and bounds the page's size (`BYTES_PER_VERTEX`) and the
time a browser takes to draw it.  A PLY file has no grid: it is shown as points, decimated to
`POINT_BUDGET` by taking every `stride`-th point.

The figure is coloured by depth (mm) or by the scan's texture (grey), switched in the page.
plotly is the optional ``report`` extra (``pip install 'sliscan[report]'``), imported only here.
"""

from __future__ import annotations

import base64
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sliscan._validate import InputError
from sliscan.types import Calibration

#: Most vertices of a mesh view.  On a 5 MP scan this is a stride of about 4 pixels, well under
#: a 4-bit stripe's width, and the page draws in about 3 s in software-rendered headless Chromium
#: (README, "Report and viewer").
MESH_BUDGET = 150_000
#: Most points of a point view (a PLY file): plotly draws points several times slower than a mesh.
POINT_BUDGET = 60_000
#: A mesh triangle whose longest edge exceeds this many times the median longest edge spans a
#: depth discontinuity and is left out.
MAX_EDGE_FACTOR = 8.0
#: Upper bound on the bytes a mesh view adds to a page per vertex: x, y, z and the depth as
#: float32, the texture as uint8, at most two triangles of three int32 indices, all base64
#: encoded (4/3), plus 10 % for the JSON around them.
BYTES_PER_VERTEX = int((4 * 4 + 1 + 2 * 3 * 4) * 4 / 3 * 1.1)
#: The same for a point view: x, y, z, depth (float32) and texture (uint8).
BYTES_PER_POINT = int((4 * 4 + 1) * 4 / 3 * 1.1)


def require_plotly() -> Any:
    """The `plotly.graph_objects` module, or a one-line `InputError` telling how to install it."""
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise InputError("the HTML report and viewer need plotly: pip install 'sliscan[report]'") from None
    return go


@dataclass(frozen=True, eq=False)
class Cloud:
    """What the 3D view shows.

    Attributes
    ----------
    vertices : (N, 3) float32 array
        World points in mm.
    faces : (F, 3) int32 array or None
        Triangles (indices into `vertices`); None for a point view.
    depth : (N,) float32 array
        Colour by depth, mm.
    texture : (N,) uint8 array or None
        Grey level of each vertex (0-255); None when the source has none.
    total : int
        Points of the full scan.
    stride : (int, int)
        A grid's row and column stride, or ``(1, k)`` for every `k`-th point of a list.
    depth_label : str
        What `depth` is (for the colour bar).
    eye, up : (3,) float64 arrays
        Initial viewing direction (from the scene's centre towards the eye) and up vector.
    isolated : int
        Points of the decimated grid in no triangle (a mesh does not draw them).
    """

    vertices: NDArray[np.float32]
    faces: NDArray[np.int32] | None
    depth: NDArray[np.float32]
    texture: NDArray[np.uint8] | None
    total: int
    stride: tuple[int, int]
    depth_label: str
    eye: NDArray[np.float64]
    up: NDArray[np.float64]
    isolated: int = 0

    def describe(self) -> str:
        """One sentence saying what is shown out of what."""
        kept = len(self.vertices)
        rows, columns = self.stride
        if self.faces is None:
            every = "" if columns == 1 else f", one point in every {columns}"
            return f"{kept:,} of the scan's {self.total:,} points{every}"
        every = "" if (rows, columns) == (1, 1) else f", one pixel per {rows}x{columns} block (rows x columns)"
        alone = f" ({self.isolated:,} isolated points of that grid are in no triangle)" if self.isolated else ""
        return (f"a mesh of {len(self.faces):,} triangles on {kept:,} of the scan's {self.total:,} points{every}"
                f"{alone}")


def grid_strides(valid: NDArray[np.bool_], budget: int) -> tuple[int, int]:
    """The densest grid stride ``(rows, columns)`` for which ``valid[::rows, ::columns]`` keeps
    at most `budget` pixels; the two differ by at most one (1x1, 1x2, 2x2, 2x3, 3x3, ...).

    >>> grid_strides(np.ones((1944, 2592), bool), 150_000)
    (6, 6)
    """
    if budget < 1:
        raise InputError(f"the point budget must be at least 1, got {budget}")
    n = int(np.count_nonzero(valid))
    rows = max(1, int(np.sqrt(n / budget)))
    columns = rows
    while int(np.count_nonzero(valid[::rows, ::columns])) > budget:
        rows, columns = (rows, columns + 1) if columns == rows else (rows + 1, columns)
    return rows, columns


def grid_faces(points: NDArray[np.floating], valid: NDArray[np.bool_], *,
               max_edge_factor: float = MAX_EDGE_FACTOR) -> tuple[NDArray[np.int32], NDArray[np.intp]]:
    """Triangles between neighbouring valid pixels of a point grid.

    Parameters
    ----------
    points : (H, W, 3) array
        World points, mm.
    valid : (H, W) bool array
    max_edge_factor : float
        Leave out triangles whose longest edge exceeds this many times the median (depth
        discontinuities).

    Returns
    -------
    faces : (F, 3) int32 array
        Indices into `used`.
    used : (N,) int array
        Flat pixel indices (into ``valid.ravel()``) of the vertices, those in some triangle.
    """
    h, w = valid.shape
    index = np.arange(h * w).reshape(h, w)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    flat = valid.ravel()
    quads = np.stack([a.ravel(), b.ravel(), c.ravel(), d.ravel()], axis=1)
    ok = flat[quads]
    faces = np.concatenate([quads[ok[:, 0] & ok[:, 1] & ok[:, 2]][:, [0, 1, 2]],
                            quads[ok[:, 1] & ok[:, 3] & ok[:, 2]][:, [1, 3, 2]]])
    if len(faces) == 0:
        return np.zeros((0, 3), np.int32), np.zeros(0, np.intp)
    xyz = points.reshape(-1, 3).astype(np.float64)
    corners = xyz[faces]  # (F, 3 vertices, 3)
    longest = np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2), axis=1)
    faces = faces[longest <= max_edge_factor * np.median(longest)]
    used, faces = np.unique(faces, return_inverse=True)
    return faces.reshape(-1, 3).astype(np.int32), used


def camera_pose(calibration: Calibration) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The camera's viewing direction and image-up vector in world coordinates (unit vectors).

    The view then starts where the camera stood: looking along the optical axis, rows down.
    """
    import cv2

    _, rotation, *_ = cv2.decomposeProjectionMatrix(np.asarray(calibration.camera.matrix, dtype=np.float64))
    right, down, forward = rotation
    return -forward, -down


def pose_from_points(points: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A viewing direction for a cloud without a calibration, and world -Y as up where it can.

    A cloud far from the world origin (more than twice its own size) was most likely measured
    in a camera-centred frame (the virtual rig's, a board calibration's): it is viewed from the
    origin.  Otherwise along its thinnest principal axis, from the origin's side.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = np.median(p, axis=0)
    sample = p[:: max(1, len(p) // 20_000)] - centre
    size = float(np.sqrt(np.median(np.sum(sample**2, axis=1))))
    if np.linalg.norm(centre) > 2 * size:
        towards = -centre / np.linalg.norm(centre)
    else:
        towards = np.linalg.svd(sample, full_matrices=False)[2][-1]
        towards = -towards if towards @ (-centre) < 0 else towards
    up = np.array([0.0, -1.0, 0.0]) - towards * -towards[1]
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    return towards, up / np.linalg.norm(up)


def camera_depth(points: NDArray[np.floating], calibration: Calibration) -> NDArray[np.float32]:
    """Depth (mm) of world points along the camera's optical axis: ``(..., 3) -> (...)``."""
    m = np.asarray(calibration.camera.matrix, dtype=np.float64)
    sign = np.sign(np.linalg.det(m[:, :3]))
    return (sign * (points @ m[2, :3] + m[2, 3]) / np.linalg.norm(m[2, :3])).astype(np.float32)


def _grey(texture: NDArray[np.floating] | None) -> NDArray[np.uint8] | None:
    return None if texture is None else np.clip(np.rint(np.asarray(texture) * 255), 0, 255).astype(np.uint8)


def cloud_from_grid(points: NDArray[np.floating], valid: NDArray[np.bool_], *,
                    texture: NDArray[np.floating] | None = None, calibration: Calibration | None = None,
                    budget: int = MESH_BUDGET) -> Cloud:
    """The mesh view of an organised scan (one point per camera pixel), decimated by
    `grid_strides` to at most `budget` vertices.

    Parameters
    ----------
    points : (H, W, 3) array
        World points, mm; only `valid` ones are used.
    valid : (H, W) bool array
    texture : (H, W) array in [0, 1], optional
    calibration : Calibration, optional
        Colour by depth along its camera's axis and start from its camera's pose; without it,
        colour by Zw and `pose_from_points`.
    budget : int
    """
    valid = np.asarray(valid, dtype=bool) & np.all(np.isfinite(points), axis=-1)
    rows, columns = grid_strides(valid, budget)
    sub = np.ascontiguousarray(points[::rows, ::columns], dtype=np.float32)
    sub_valid = valid[::rows, ::columns]
    faces, used = grid_faces(sub, sub_valid)
    vertices = sub.reshape(-1, 3)[used]
    if calibration is not None:
        depth, label, (eye, up) = camera_depth(vertices, calibration), "depth (mm)", camera_pose(calibration)
    else:
        depth, label = vertices[:, 2].copy(), "Zw (mm)"
        eye, up = pose_from_points(vertices) if len(vertices) else (np.array([0.0, 0.0, -1.0]), np.array([0.0, -1.0, 0.0]))
    grey = None if texture is None else _grey(np.asarray(texture)[::rows, ::columns].ravel()[used])
    return Cloud(vertices=vertices, faces=faces, depth=depth, texture=grey, total=int(valid.sum()), stride=(rows, columns),
                 depth_label=label, eye=eye, up=up, isolated=int(sub_valid.sum()) - len(used))


def cloud_from_points(points: NDArray[np.floating], *, grey: NDArray[np.floating] | None = None,
                      budget: int = POINT_BUDGET) -> Cloud:
    """The point view of an unorganised cloud ``(N, 3)`` (mm), every `stride`-th point kept so
    that at most `budget` remain; coloured by Zw or `grey` (in [0, 1])."""
    if budget < 1:
        raise InputError(f"the point budget must be at least 1, got {budget}")
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    finite = np.all(np.isfinite(p), axis=1)
    p = p[finite]
    stride = max(1, -(-len(p) // budget))
    kept = p[::stride]
    shade = None if grey is None else _grey(np.asarray(grey).reshape(-1)[finite][::stride])
    eye, up = pose_from_points(kept) if len(kept) else (np.array([0.0, 0.0, -1.0]), np.array([0.0, -1.0, 0.0]))
    return Cloud(vertices=kept, faces=None, depth=kept[:, 2].copy(), texture=shade, total=len(p), stride=(1, stride),
                 depth_label="Zw (mm)", eye=eye, up=up)


def load_cloud(path: str | os.PathLike, *, mesh_budget: int = MESH_BUDGET, point_budget: int = POINT_BUDGET) -> Cloud:
    """The view of a scan file: a PLY point cloud (points), a sliscan npz scan or a mat5 prefix
    (organised: a mesh).

    Raises
    ------
    InputError
        If the file cannot be read as any of these (the message names it), or holds no point.
    """
    from sliscan.formats import mat5, npz, ply

    p = Path(path)
    if p.suffix.lower() == ".ply":
        points, grey = ply.read_point_cloud(p)
        cloud = cloud_from_points(points, grey=grey, budget=point_budget)
    elif p.suffix.lower() == ".npz":
        result = npz.read_scan_npz(p)
        cloud = cloud_from_grid(result.points, result.valid, texture=result.texture, budget=mesh_budget)
    elif mat5.mat5_paths(p)[-1].exists():
        points, valid, texture = mat5.read_mat5(p)
        cloud = cloud_from_grid(points, valid, texture=texture, budget=mesh_budget)
    else:
        raise InputError(f"{p}: not a .ply or .npz file, nor a mat5 prefix ({mat5.mat5_paths(p)[-1]} not found)")
    if len(cloud.vertices) == 0:
        raise InputError(f"{p}: the scan has no valid point to show")
    return cloud


def plotly_script() -> str:
    """The whole plotly.js library as one inline ``<script>`` (about 4.8 MB): the page then needs
    no network."""
    require_plotly()
    from plotly.offline import get_plotlyjs

    return f'<script type="text/javascript">{get_plotlyjs()}</script>'


# The colour switch: keeps the depth colours plotly decoded, and decodes the texture (base64
# uint8) on first use.
_SWITCH_JS = """
window.sliscanColour = function (id, mode) {
  var div = document.getElementById(id), v = window.sliscanViews[id];
  var key = v.points ? "marker.color" : "intensity", update = {};
  if (v.depth === undefined) { v.depth = v.points ? div.data[0].marker.color : div.data[0].intensity; }
  if (mode === "texture" && v.grey === undefined) {
    var bytes = atob(v.texture), grey = new Float32Array(bytes.length);
    for (var k = 0; k < bytes.length; k++) { grey[k] = bytes.charCodeAt(k); }
    v.grey = grey;
  }
  update[key] = [mode === "texture" ? v.grey : v.depth];
  update[(v.points ? "marker." : "") + "colorscale"] = [mode === "texture" ? [[0, "#000"], [1, "#fff"]] : "Viridis"];
  update[(v.points ? "marker." : "") + "colorbar.title.text"] = [mode === "texture" ? "texture" : v.label];
  Plotly.restyle(div, update, [0]);
};
"""


def _trace(cloud: Cloud) -> Any:
    """The plotly trace of a cloud, coloured by depth."""
    go = require_plotly()
    x, y, z = (np.ascontiguousarray(cloud.vertices[:, k]) for k in range(3))
    colorbar = {"title": {"text": cloud.depth_label}, "len": 0.75}
    if cloud.faces is None:
        return go.Scatter3d(x=x, y=y, z=z, mode="markers", hoverinfo="x+y+z",
                            marker={"size": 1.2, "color": cloud.depth, "colorscale": "Viridis", "colorbar": colorbar})
    i, j, k = (np.ascontiguousarray(cloud.faces[:, n]) for n in range(3))
    return go.Mesh3d(x=x, y=y, z=z, i=i, j=j, k=k, intensity=cloud.depth, colorscale="Viridis", colorbar=colorbar,
                     hoverinfo="x+y+z", flatshading=False,
                     lighting={"ambient": 0.55, "diffuse": 0.7, "specular": 0.1, "roughness": 0.9})


def view_div(cloud: Cloud, *, div_id: str = "view3d", height_px: int = 640) -> str:
    """The 3D view as an HTML fragment: the plot's div, its script, and the colour switch.

    The page must load `plotly_script` before it.  When plotly has drawn the figure, the div
    gets ``data-rendered="1"`` (tests and benchmarks wait for it).
    """
    go = require_plotly()
    # From the camera's side, turned a little sideways and down (away from a projector above the
    # camera, which sees its own stripe planes edge-on), so the relief shows at once.
    turned = cloud.eye + 0.35 * np.cross(cloud.up, cloud.eye) - 0.25 * cloud.up
    eye = 1.9 * turned / np.linalg.norm(turned)
    layout = {
        "template": "plotly_white", "height": height_px, "margin": {"l": 0, "r": 0, "t": 0, "b": 0},
        "scene": {"aspectmode": "data", "xaxis": {"title": {"text": "Xw (mm)"}},
                  "yaxis": {"title": {"text": "Yw (mm)"}}, "zaxis": {"title": {"text": "Zw (mm)"}},
                  "camera": {"eye": dict(zip("xyz", eye.tolist())),
                             "up": dict(zip("xyz", cloud.up.tolist()))}},
    }
    fig = go.Figure(_trace(cloud), layout=layout)
    store = {"points": cloud.faces is None, "label": cloud.depth_label,
             "texture": None if cloud.texture is None else base64.b64encode(cloud.texture.tobytes()).decode("ascii")}
    post = f'document.getElementById("{div_id}").dataset.rendered = "1";'
    plot = fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id, post_script=post,
                       config={"displaylogo": False, "responsive": True})
    disabled = "" if cloud.texture is not None else " disabled"
    return (f'<div class="view-controls">colour by <select onchange="sliscanColour(\'{div_id}\', this.value)">'
            f'<option value="depth">{cloud.depth_label}</option><option value="texture"{disabled}>texture</option>'
            f'</select> · drag to rotate, scroll to zoom, right-drag to pan</div>'
            f'<script>window.sliscanViews = window.sliscanViews || {{}}; '
            f'window.sliscanViews["{div_id}"] = {json.dumps(store)};{_SWITCH_JS}</script>{plot}')
