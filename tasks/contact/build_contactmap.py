"""The ``build_contactmap`` stage (the paper's stage 4, ContactDB protocol): per-vertex contact
from the post-grasp thermal turntable scan.

For every thermal view the object's pose in the thermal camera is
``T_thermal_o = inv(T_color_thermal) @ T_color_turntable @ Rz(angle) @ T_turntable_o_scan``.
A vertex is seen by a view when it projects inside the image, the first hit of
the ray from the camera centre towards it (Open3D ``RaycastingScene``) lies
within ``visibility_eps_m`` of the vertex, and the view is not grazing
(``|cos|`` between the ray and the vertex normal >= ``cos_min``). Seen vertices
sample the thermal image bilinearly; the views are fused by a weighted median
(weights ``|cos|``), so one bad view cannot pull a vertex.

Temperatures become contact the ContactDB way, a per-map normalisation into [0, 1]:

- ambient: the lowest-temperature peak of the histogram of the fused
  temperatures (most of an object is untouched and sits at ambient; taking the
  *lowest* clear peak keeps a widely, weakly warmed surface from being read as
  ambient), or a fixed ``ambient_k``;
- full contact: the ``full_rise_rank``-th largest observed rise over ambient
  (ContactDB stores its maps scaled so their maximum is near 1; the rank keeps
  a few outlier vertices from setting the scale), or a fixed ``full_rise_k``;
- ``contact = clip(rise / full_rise, 0, 1)``. When the full rise is below
  ``min_contact_rise_k`` the scan is all ambient: ``all_ambient`` is set and
  every contact is 0 (not an error).

Unobserved vertices get contact 0 and ``observed = False``: unobserved is not "no contact".

A pixel of 0 K is no reading (a dropped frame, a padded border): vertices sampled from one are
not seen by that view. A view without a reading or with one constant value holds no thermal
image and is left out with a note in ``ContactMap.notes``; when every view is such, the stage
fails naming the files. One usable view builds a map, with a note on the share it covers.

A mesh of more than ``proxy_faces`` faces is projected and ray cast as its proxy
(:mod:`mesh_proxy`): every vertex takes the views' samples of the proxy vertex standing for it,
then fusion and normalisation run per vertex of the session's mesh, in file order (a note says
so).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from pydantic import Field

from graspcap.tasks.core.camera import Camera
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError, check_mesh
from graspcap.tasks.core.geometry import inv_T, rot_z, transform_points
from graspcap.tasks.core.mesh_proxy import PROXY_FACES, mesh_proxy

# open3d: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "build_contactmap/4"
STAGE = "build_contactmap"


class AmbientMode(StrEnum):
    """Where the ambient temperature comes from."""

    LOWEST_PEAK = "lowest_peak"
    """The lowest clear peak of the fused temperatures of the observed vertices."""
    FIXED = "fixed"
    """``ambient_k`` from the config (a measured room temperature)."""


class RiseMode(StrEnum):
    """What temperature rise counts as full contact (contact 1)."""

    MAX = "max"
    """The (robust) largest observed rise: ContactDB's per-map normalisation to a maximum of 1."""
    FIXED = "fixed"
    """``full_rise_k`` from the config (a calibrated skin-to-object rise)."""


class BuildContactmapConfig(StageConfig):
    """Visibility, fusion and normalisation settings."""

    visibility_eps_m: float = 0.0015
    """A vertex is visible when the first ray hit is at most this much closer than the vertex."""
    cos_min: float = 0.3
    """Grazing cut-off: views with |cos(ray, vertex normal)| below this do not see the vertex."""
    border_px: float = 1.0
    """Projections closer than this to the image border are not sampled."""
    min_views: int = 1
    """A vertex seen by fewer views is unobserved."""
    ambient_mode: AmbientMode = AmbientMode.LOWEST_PEAK
    """How ambient is found."""
    ambient_k: float = 295.0
    """Ambient temperature in kelvin, used only with ``ambient_mode = fixed``."""
    ambient_bin_k: float = 0.05
    """Histogram bin width for the ambient peak search."""
    ambient_peak_share: float = 0.2
    """A histogram peak counts when it is at least this share of the highest peak."""
    rise_mode: RiseMode = RiseMode.MAX
    """How the full-contact rise is found."""
    full_rise_rank: int = 5
    """The ``full_rise_rank``-th largest observed rise is full contact (``rise_mode = max``):
    the maximum, robust to a few outlier vertices."""
    full_rise_k: float = 4.0
    """Rise of full contact in kelvin, used only with ``rise_mode = fixed``."""
    min_contact_rise_k: float = 1.0
    """A full-contact rise below this means nothing was touched: the scan is all ambient."""
    proxy_faces: int = Field(PROXY_FACES, ge=1000)
    """A mesh with more faces is projected and ray cast as a proxy of about this many
    (:mod:`mesh_proxy`); the map is still given for every vertex of the mesh (979200-face mug:
    6.1 s on the mesh, 3.5 s on its proxy, contact 0.003 apart on average; a 1.31-million-face
    sphere: 18.4 s and 5.4 s)."""
    align_to_hand: bool = True
    """On a symmetric object, carry the map into the grasp's frame by the turn that brings its
    contacted vertices nearest the fitted hand (``symmetric_contact``; the stage's glue, which
    has the hand)."""
    symmetry_tolerance_m: float = Field(0.005, gt=0)
    """A turn about the centroid is a symmetry of the object when it moves no sampled surface
    point further than this off the surface (the tracking's ``revolution_tolerance_m``)."""
    align_near_mm: float = Field(10.0, gt=0)
    """A contacted vertex within this of the fitted hand counts as on it when turns are
    scored: a fit is millimetres off, a wrong turn puts the contact centimetres away."""
    align_margin: float = Field(0.15, ge=0)
    """The best turn's score must beat the scan's own frame's by this to be taken..."""
    align_ratio: float = Field(2.0, ge=1)
    """...and be at least this multiple of it: a fitted hand centimetres off can sit nearer a
    wrong turn of a correct map by chance (wild ``[94397, 29]``, a glass: 0.45 against 0.29,
    which would have turned a map of IoU 0.87 to 0.02; tuning, ``docs/benchmarks.md``)."""
    align_contact_threshold: float = 0.4
    """Contact at or above this counts as contacted when turns are scored."""
    align_bare_frames: int = Field(16, ge=0)
    """A turn's score is lowered where it puts contact on surface the grasp's depth saw bare,
    over up to this many of the frames the object was tracked in (0: the hand alone scores)."""
    align_bare_m: float = Field(0.006, gt=0)
    """A vertex is seen bare where the depth's reading at its pixel lies within this of it, and
    covered where the reading lies more than this in front of it (Kinect-like noise at 1 m is
    2-3 mm)."""
    align_bare_window_px: int = Field(3, ge=0)
    """...and bare only where no reading within this many pixels lies in front of it."""


PRESETS: dict[str, BuildContactmapConfig] = {
    "default": BuildContactmapConfig(),
    "fixed_rise": BuildContactmapConfig(rise_mode=RiseMode.FIXED),
    "strict_visibility": BuildContactmapConfig(cos_min=0.5, min_views=2),
}


@dataclass(frozen=True)
class ContactMap:
    """Result of :func:`build_contactmap`.

    Attributes
    ----------
    contact : (n,) float32
        Contact in [0, 1] per mesh vertex (file order); 0 where unobserved.
    observed : (n,) bool
        Seen by at least ``min_views`` views.
    n_views_seen : (n,) int
        Views that saw each vertex.
    temperature_k : (n,) float32
        Fused temperature; NaN where unobserved.
    ambient_k, full_rise_k : float
        Ambient and the rise mapped to contact 1.
    all_ambient : bool
        No rise worth calling contact anywhere (contact is all 0).
    per_view_visible : (views,) int
        Vertices each view saw.
    coverage : float
        Share of vertices observed.
    n_degenerate_faces : int
        Zero-area faces, left out of the vertex normals.
    notes : tuple of str
        What a person may want to know that changes no value: views left out (no reading or
        constant), a map from one view only; a map turned into the grasp's frame.
    turned_deg : float
        The turn of a symmetric object by which the map was carried from the scan's frame into
        the grasp's (``symmetric_contact.align_to_hand``); 0 where it was not.
    """

    contact: np.ndarray
    observed: np.ndarray
    n_views_seen: np.ndarray
    temperature_k: np.ndarray
    ambient_k: float
    full_rise_k: float
    all_ambient: bool
    per_view_visible: np.ndarray
    coverage: float
    n_degenerate_faces: int
    notes: tuple[str, ...] = ()
    turned_deg: float = 0.0


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int]:
    """Area-weighted unit vertex normals, zero-area faces skipped.

    Returns ``(normals (n, 3) float, n_degenerate)``; a vertex with no valid face has a 0 normal.
    """
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    good = area2 > 1e-12 * scale * scale
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[good, k], cross[good])
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return normals, int((~good).sum())


def _count_degenerate(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Zero-area faces, as :func:`vertex_normals` counts them."""
    tri = vertices[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    return int((area2 <= 1e-12 * scale * scale).sum())


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample ``image (h, w)`` at ``uv (k, 2)`` pixel coordinates (pixel centres at integers)."""
    h, w = image.shape
    if h < 2 or w < 2:
        raise StageError(STAGE, f"a thermal image of {w}x{h} px cannot be sampled (need 2x2)")
    u = np.clip(uv[:, 0], 0, w - 1.000001)
    v = np.clip(uv[:, 1], 0, h - 1.000001)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    du, dv = u - u0, v - v0
    return ((1 - du) * (1 - dv) * image[v0, u0] + du * (1 - dv) * image[v0, u0 + 1]
            + (1 - du) * dv * image[v0 + 1, u0] + du * dv * image[v0 + 1, u0 + 1])


def weighted_median(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Row-wise weighted median of ``values (n, k)`` (NaN = missing) with ``weights (n, k)``.

    Rows with no value give NaN. Ties at exactly half the weight take the lower value.
    """
    w = np.where(np.isnan(values), 0.0, weights)
    order = np.argsort(np.where(np.isnan(values), np.inf, values), axis=1)
    v_sorted = np.take_along_axis(values, order, axis=1)
    cum = np.cumsum(np.take_along_axis(w, order, axis=1), axis=1)
    total = cum[:, -1:]
    idx = np.argmax(cum >= 0.5 * total, axis=1)
    out = v_sorted[np.arange(len(values)), idx]
    return np.where(total[:, 0] > 0, out, np.nan)


def lowest_peak(temps: np.ndarray, bin_k: float, peak_share: float) -> float:
    """The lowest clear mode of ``temps (k,)``: the lowest local maximum of a smoothed histogram
    that is at least ``peak_share`` of the highest, refined as the median of its nearby samples."""
    lo, hi = np.percentile(temps, [0.1, 99.9])
    n_bins = int(np.clip(np.ceil((hi - lo) / bin_k), 1, 4000))
    counts, edges = np.histogram(temps, bins=n_bins, range=(lo, hi + 1e-9))
    # zero-padded, so a histogram of fewer than 3 bins (one temperature) keeps its length
    smooth = np.convolve(np.pad(counts, 1), [0.25, 0.5, 0.25], mode="valid")
    padded = np.concatenate([[-1.0], smooth, [-1.0]])
    peaks = np.flatnonzero((padded[1:-1] >= padded[:-2]) & (padded[1:-1] > padded[2:])
                           & (smooth >= peak_share * smooth.max()))
    centre = 0.5 * (edges[peaks[0]] + edges[peaks[0] + 1])
    near = temps[np.abs(temps - centre) <= 1.5 * bin_k]
    return float(np.median(near)) if len(near) else float(centre)


def _view_name(k: int, names: Sequence[str] | None) -> str:
    return f"thermal view {k}" + (f" ({names[k]})" if names is not None else "")


def _check_inputs(vertices, faces, views, K, image_size, names, mesh_name) -> tuple[int, int]:
    check_mesh(STAGE, vertices, faces, name=mesh_name)
    if not views:
        raise StageError(STAGE, "no thermal views (scan.views is empty)")
    if names is not None and len(names) != len(views):
        raise ValueError(f"{len(names)} view names for {len(views)} views")
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise StageError(STAGE, "thermal_camera.K must be a finite 3x3 matrix")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise StageError(STAGE, f"thermal_camera.K has focal lengths {K[0, 0]}, {K[1, 1]}: "
                                "they must be positive (pixels)")
    width, height = image_size if image_size is not None else views[0][0].shape[::-1]
    for k, (image, _) in enumerate(views):
        if np.ndim(image) != 2:
            raise StageError(STAGE, f"{_view_name(k, names)} has shape {np.shape(image)}, "
                                    "expected one channel of temperatures (h, w)")
        if image.shape != (height, width):
            raise StageError(STAGE, f"{_view_name(k, names)} is {image.shape[1]}x"
                                    f"{image.shape[0]} px, expected {width}x{height} "
                                    "(thermal_camera width, height)")
        if not np.isfinite(image).all():
            raise StageError(STAGE, f"{_view_name(k, names)} holds non-finite temperatures")
    return width, height


def _blank_views(views) -> dict[int, str]:
    """Views that hold no thermal image, by index: why (no reading, or one constant value)."""
    blank = {}
    for k, (image, _) in enumerate(views):
        image = np.asarray(image)
        hi = float(image.max())
        if hi <= 0:
            blank[k] = "all 0 K (no reading)"
        elif float(image.min()) == hi:
            blank[k] = (f"one constant {hi:.2f} K (no thermal contrast: a blank or placeholder "
                        "frame)")
    return blank


def _views_named(ks: Sequence[int], names: Sequence[str] | None, at_most: int = 4) -> str:
    """``thermal view(s) 0 (file), 3 (file)``, at most ``at_most`` named, then a count."""
    shown = [f"{k}" + (f" ({names[k]})" if names is not None else "") for k in ks[:at_most]]
    more = f" and {len(ks) - at_most} more" if len(ks) > at_most else ""
    return f"thermal view{'s' if len(ks) > 1 else ''} {', '.join(shown)}{more}"


def _blank_text(blank: dict[int, str], names: Sequence[str] | None) -> list[str]:
    """One phrase per reason: which views (named) are blank and why."""
    by_why: dict[str, list[int]] = {}
    for k, why in blank.items():
        by_why.setdefault(why, []).append(k)
    return [f"{_views_named(ks, names)} {'is' if len(ks) == 1 else 'are'} {why}"
            for why, ks in by_why.items()]


def build_contactmap(
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    views: list[tuple[np.ndarray, float]],
    K_thermal: np.ndarray,
    T_color_thermal: np.ndarray,
    T_color_turntable: np.ndarray,
    T_turntable_o_scan: np.ndarray,
    config: BuildContactmapConfig = PRESETS["default"],
    *,
    image_size: tuple[int, int] | None = None,
    dist_thermal: np.ndarray | None = None,
    view_names: Sequence[str] | None = None,
    mesh_name: str = "the object mesh",
) -> ContactMap:
    """Fuse the thermal scan views into per-vertex contact (module docstring has the method).

    Parameters
    ----------
    mesh_vertices : (n, 3) float
        Object mesh in its own frame, metres.
    mesh_faces : (m, 3) int
    views : list of (thermal_k (h, w) float, angle_rad float)
        Thermal images in kelvin and the platter angle of each view.
    K_thermal : (3, 3) float
        Thermal intrinsics (OpenCV).
    T_color_thermal, T_color_turntable, T_turntable_o_scan : (4, 4) float
        Rig extrinsics and the object's registered pose on the platter at angle 0.
    image_size : (width, height), optional
        The thermal camera's declared size; every view must match it (else they must agree).
    dist_thermal : (k,) float, optional
        The thermal lens's OpenCV distortion (``thermal_camera.dist``): vertices are projected
        into the raw thermal images through it (``Camera.project``); None or zeros: pinhole.
    view_names, mesh_name : optional
        The views' thermal files and the mesh file, for messages.

    Raises
    ------
    StageError
        Malformed mesh, a view of the wrong size, no view with a thermal image, or no view
        that sees the object.
    """
    import open3d as o3d

    vertices = np.asarray(mesh_vertices, dtype=np.float64)
    faces = np.asarray(mesh_faces, dtype=np.int64)
    K = np.asarray(K_thermal, dtype=np.float64)
    width, height = _check_inputs(vertices, faces, views, K, image_size, view_names, mesh_name)
    blank = _blank_views(views)
    if len(blank) == len(views):
        raise StageError(STAGE, "no thermal view holds a thermal image: "
                                f"{'; '.join(_blank_text(blank, view_names))}; check the scan's "
                                "thermal PNGs (centi-kelvin, uint16) and the thermal camera")
    notes = [f"{text}: left out" for text in _blank_text(blank, view_names)]
    proxy = mesh_proxy(vertices, faces, config.proxy_faces)
    if proxy.is_original:
        normals, n_degenerate = vertex_normals(vertices, faces)
    else:
        notes.append(proxy.note(len(faces), "visibility and sampling"))
        n_degenerate = _count_degenerate(vertices, faces)
        vertices, faces = proxy.vertices, proxy.faces
        normals = vertex_normals(vertices, faces)[0]

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(vertices.astype(np.float32), faces.astype(np.uint32))
    n, n_views = len(vertices), len(views)
    temps = np.full((n, n_views), np.nan)
    weights = np.zeros((n, n_views))
    T_thermal_turntable = inv_T(T_color_thermal) @ T_color_turntable
    lens = Camera(K, np.zeros(4) if dist_thermal is None else dist_thermal, width, height)
    b = config.border_px
    for k, (image, angle_rad) in enumerate(views):
        if k in blank:
            continue
        T_th_o = T_thermal_turntable @ rot_z(angle_rad) @ T_turntable_o_scan
        p = transform_points(T_th_o, vertices)
        z = p[:, 2]
        front = z > 1e-6
        uv = np.full((n, 2), -1.0)
        if lens.distorted:  # NaN (outside the lens's field) fails the inside test below
            uv[front] = lens.project(p[front])
        else:
            uv[front] = (p[front] @ K.T)[:, :2] / z[front, None]
        inside = front & (uv[:, 0] >= b) & (uv[:, 0] <= width - 1 - b) & (
            uv[:, 1] >= b) & (uv[:, 1] <= height - 1 - b)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        centre_o = inv_T(T_th_o)[:3, 3]
        ray = vertices[idx] - centre_o
        dist = np.linalg.norm(ray, axis=1)
        ray /= dist[:, None]
        cos = np.abs((normals[idx] * ray).sum(1))
        rays = np.concatenate([np.broadcast_to(centre_o, ray.shape), ray], 1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        seen = (t_hit >= dist - config.visibility_eps_m) & (cos >= config.cos_min)
        idx, cos = idx[seen], cos[seen]
        image = np.asarray(image, dtype=np.float64)
        sampled = bilinear(image, uv[idx])
        read = bilinear((image > 0).astype(np.float64), uv[idx]) > 1.0 - 1e-9  # no 0 K neighbour
        temps[idx[read], k] = sampled[read]
        weights[idx[read], k] = cos[read]

    fused = weighted_median(temps, weights)
    seen = weights > 0
    if proxy.is_original:
        n_views_seen, per_view_visible = seen.sum(1), seen.sum(0).astype(np.int64)
    else:  # every vertex of the mesh takes its proxy vertex's fused samples
        stands_for = np.bincount(proxy.of_vertex, minlength=n)  # original vertices per proxy
        per_view_visible = (seen * stands_for[:, None]).sum(0).astype(np.int64)
        n_views_seen, fused = seen.sum(1)[proxy.of_vertex], fused[proxy.of_vertex]
        n = len(fused)
    observed = n_views_seen >= max(config.min_views, 1)
    if not observed.any():
        raise StageError(STAGE, "no thermal view sees the object (check T_turntable_o_scan, "
                                "T_color_thermal and T_color_turntable)")
    used = n_views - len(blank)
    if used == 1:
        notes.append(f"one thermal view only: the contact map covers what one view sees "
                     f"({100 * observed.mean():.0f} % of the vertices observed)")
    fused[~observed] = np.nan
    seen_t = fused[observed]
    if config.ambient_mode is AmbientMode.FIXED:
        ambient = float(config.ambient_k)
    else:
        ambient = lowest_peak(seen_t, config.ambient_bin_k, config.ambient_peak_share)
    rise = seen_t - ambient
    top_rise = float(np.sort(rise)[-min(max(config.full_rise_rank, 1), len(rise))])
    full_rise = float(config.full_rise_k) if config.rise_mode is RiseMode.FIXED else top_rise
    all_ambient = top_rise < config.min_contact_rise_k
    contact = np.zeros(n, dtype=np.float32)
    if not all_ambient:
        contact[observed] = np.clip(rise / full_rise, 0.0, 1.0)
    return ContactMap(
        contact=contact, observed=observed, n_views_seen=n_views_seen.astype(np.int64),
        temperature_k=fused.astype(np.float32), ambient_k=ambient, full_rise_k=full_rise,
        all_ambient=bool(all_ambient), per_view_visible=per_view_visible,
        coverage=float(observed.mean()), n_degenerate_faces=n_degenerate, notes=tuple(notes),
    )
